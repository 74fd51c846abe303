"""Fitting a material field to reference videos (PhysDreamer stages 1 and 2).

Building blocks exported here: neural fields (fields.py), image losses (losses.py) and
reference-video input (video.py). The optimisation loop builds on them.
"""
from pd_tool.fit.fields import (
    FieldSettingsError,
    MaterialField,
    Triplane,
    TriplaneField,
    VelocityField,
    tv_loss,
)
from pd_tool.fit.losses import frame_loss, ssim, ssim_map
from pd_tool.fit.video import ReferenceVideo, load_reference_video, write_video_folder

__all__ = [
    "FieldSettingsError",
    "MaterialField",
    "ReferenceVideo",
    "Triplane",
    "TriplaneField",
    "VelocityField",
    "frame_loss",
    "load_reference_video",
    "ssim",
    "ssim_map",
    "tv_loss",
    "write_video_folder",
]
