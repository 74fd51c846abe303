"""Fitting a material field to reference videos (PhysDreamer stages 1 and 2).

Building blocks exported here: neural fields (fields.py), image losses (losses.py),
reference-video input (video.py), AdamW + lr schedule (schedule.py). The optimisation
loop builds on them.
"""
from pd_tool.fit.fields import (
    FieldSettingsError,
    MaterialField,
    Triplane,
    TriplaneField,
    VelocityField,
    field_arrays,
    load_field,
    tv_loss,
)
from pd_tool.fit.losses import frame_loss, ssim, ssim_map
from pd_tool.fit.schedule import make_optimizer, warmup_linear_decay
from pd_tool.video.folder import ReferenceVideo, load_reference_video, write_video_folder

__all__ = [
    "FieldSettingsError",
    "MaterialField",
    "ReferenceVideo",
    "Triplane",
    "TriplaneField",
    "VelocityField",
    "field_arrays",
    "frame_loss",
    "load_field",
    "load_reference_video",
    "make_optimizer",
    "ssim",
    "ssim_map",
    "tv_loss",
    "warmup_linear_decay",
    "write_video_folder",
]
