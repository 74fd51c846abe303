"""Fitting a material field to reference videos (PhysDreamer stages 1 and 2).

The fit: settings (settings.py), the differentiable forward (problem.py), the stages and
calibration (stages.py), checkpoint and resume (resume.py), the refusals of a fit that
cannot learn (refusals.py), and the run that ties them together (run.py: run_fit).

Building blocks exported here too: neural fields (fields.py), image losses (losses.py),
reference-video input (pd_tool/video/folder.py), AdamW + lr schedule (schedule.py).
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
from pd_tool.fit.run import FitResult, run_fit
from pd_tool.fit.schedule import make_optimizer, warmup_linear_decay
from pd_tool.fit.settings import FitSettings
from pd_tool.video.folder import ReferenceVideo, load_reference_video, write_video_folder

__all__ = [
    "FieldSettingsError",
    "FitResult",
    "FitSettings",
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
    "run_fit",
    "ssim",
    "ssim_map",
    "tv_loss",
    "warmup_linear_decay",
    "write_video_folder",
]
