"""Materials: the `.pdmat` file a fit writes and a bake reads, and the shipped presets
(materials, quality levels, forces)."""
