"""Shipped TOML presets (materials, quality levels, forces); data only."""
