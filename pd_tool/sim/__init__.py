"""Differentiable MLS-MPM simulator in warp (fixed-corotated elasticity, SI units)."""
from pd_tool.sim.solver import Force, MPMSolver, SimConfig, SimConfigError

__all__ = ["Force", "MPMSolver", "SimConfig", "SimConfigError"]
