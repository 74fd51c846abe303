"""pdtool engine: make a static 3D Gaussian Splatting scan move like the real object."""
from pd_tool.core.errors import PdToolError

__version__ = "0.1.0"
__all__ = ["PdToolError", "__version__"]
