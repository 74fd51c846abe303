"""USD export: the only package that imports pxr."""
