"""What every stage shares: the scene type, cameras, quaternions, errors, atomic output and
the device choice. Nothing here imports a pipeline stage."""
