"""Reference videos: frame-folder input and output, generation from an image-to-video model,
and the camera-motion check of a generated clip."""
