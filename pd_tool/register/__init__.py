"""Camera registration: where a frame's camera sits in the splat's frame."""
from pd_tool.register.solve import Registration, RegisterSettings, register_frame

__all__ = ["Registration", "RegisterSettings", "register_frame"]
