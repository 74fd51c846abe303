"""The image-to-video pipelines that `pdtool generate` runs, one entry per diffusers class.

A model folder names its pipeline in model_index.json (`_class_name`). Each entry here says
which components such a folder must hold, the model's own defaults (frame count, size,
frame rate, denoising steps, guidance), and how the pipeline is called. `rules` reads the
frame-size and frame-count constraints from the components' configs, so that a size or
length the model cannot take is refused before any weight is loaded.

The defaults are each pipeline's own (its `__call__` defaults, or its transformer's config
where the pipeline reads them from there), except SVD's, which are the paper's, and
CogVideoX 1.5's, which are its model card's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

# Components that hold weights (checked for *.safetensors), and the config file of the others.
WEIGHT_COMPONENTS = ("unet", "transformer", "transformer_2", "vae", "image_encoder", "text_encoder")
CONFIG_FILES = {"scheduler": "scheduler_config.json", "feature_extractor": "preprocessor_config.json",
                "image_processor": "preprocessor_config.json", "tokenizer": "tokenizer_config.json"}

# Text-conditioned models get a prompt that asks for the motion the fit needs: the object
# moving freely in front of a still camera (fit assumes a still camera).
DEFAULT_PROMPT = ("The object sways gently back and forth after a light push, then settles. "
                  "Static camera, fixed tripod shot, plain background.")
DEFAULT_NEGATIVE = ("camera movement, zoom, pan, tilt, shaky camera, cut, scene change, blurry, distorted, "
                    "deformed, text, watermark")


@dataclass(frozen=True)
class Kind:
    """One diffusers image-to-video pipeline class.

    components: names that model_index.json must give a (library, class) pair (not null).
    frames / size (width, height, px) / fps / steps / guidance: the model's defaults; a
    size or frame count of None is read from the configs (`rules`). text: conditioned on
    a prompt. cuda_dtype: the dtype the model runs in on CUDA (its authors' choice).
    """

    class_name: str
    label: str
    example: str
    components: tuple[str, ...]
    frames: int | None
    size: tuple[int, int] | None
    fps: float
    steps: int
    guidance: float | None
    text: bool
    cuda_dtype: str


KINDS: dict[str, Kind] = {k.class_name: k for k in (
    Kind("StableVideoDiffusionPipeline", "Stable Video Diffusion", "stabilityai/stable-video-diffusion-img2vid",
         ("unet", "vae", "image_encoder", "scheduler", "feature_extractor"),
         frames=14, size=(1024, 576), fps=30.0, steps=25, guidance=None, text=False, cuda_dtype="float16"),
    Kind("WanImageToVideoPipeline", "Wan 2.x image-to-video", "Wan-AI/Wan2.1-I2V-14B-480P-Diffusers",
         ("transformer", "vae", "text_encoder", "tokenizer", "scheduler"),
         frames=81, size=(832, 480), fps=16.0, steps=50, guidance=5.0, text=True, cuda_dtype="bfloat16"),
    Kind("CogVideoXImageToVideoPipeline", "CogVideoX image-to-video", "THUDM/CogVideoX-5b-I2V",
         ("transformer", "vae", "text_encoder", "tokenizer", "scheduler"),
         frames=None, size=None, fps=8.0, steps=50, guidance=6.0, text=True, cuda_dtype="bfloat16"),
    Kind("LTXImageToVideoPipeline", "LTX-Video", "Lightricks/LTX-Video",
         ("transformer", "vae", "text_encoder", "tokenizer", "scheduler"),
         frames=161, size=(704, 512), fps=25.0, steps=50, guidance=3.0, text=True, cuda_dtype="bfloat16"),
)}


@dataclass(frozen=True)
class Rules:
    """What one model folder takes: width and height in multiples of `multiple` px; a frame
    count of 1 + k * `temporal` (1: any); `fixed_size` (width, height) when the model takes
    only that size; and its defaults (frames, size, fps)."""

    multiple: int
    temporal: int
    fixed_size: tuple[int, int] | None
    frames: int
    size: tuple[int, int]
    fps: float


def rules(kind: Kind, config: Callable[[str], dict]) -> Rules:
    """Read the size and length rules of a folder of `kind` from its configs.

    config(component) returns that component's config.json as a dict. Raises KeyError,
    TypeError or ValueError when a config lacks what the pipeline itself reads.
    """
    name = kind.class_name
    fixed = None
    frames, size, fps = kind.frames, kind.size, kind.fps
    if name == "StableVideoDiffusionPipeline":
        vae = 2 ** (len(config("vae")["block_out_channels"]) - 1)
        unet = 2 ** (len(config("unet")["down_block_types"]) - 1)
        multiple, temporal = math.lcm(8, vae * unet), 1
    elif name == "WanImageToVideoPipeline":
        vae, tr = config("vae"), config("transformer")
        # older Wan VAE configs omit the factors; the pipeline then uses 8 and 4, as here
        multiple = int(vae.get("scale_factor_spatial", 8)) * int(tr.get("patch_size", (1, 2, 2))[1])
        temporal = int(vae.get("scale_factor_temporal", 4))
    elif name == "CogVideoXImageToVideoPipeline":
        vae, tr = config("vae"), config("transformer")
        spatial = 2 ** (len(vae.get("block_out_channels", (128, 256, 256, 512))) - 1)
        multiple = spatial * int(tr.get("patch_size", 2))
        temporal = int(vae.get("temporal_compression_ratio", 4))
        size = (int(tr.get("sample_width", 90)) * spatial, int(tr.get("sample_height", 60)) * spatial)
        frames = int(tr.get("sample_frames", 49))
        if tr.get("patch_size_t") is not None:
            # CogVideoX 1.5 (patches in time): its config's sample size (300 x 300 latents) is
            # not a size it makes; its model card's are 1360 x 768 at 16 fps, 81 frames
            size, frames, fps = (1360, 768), 81, 16.0
        if tr.get("use_learned_positional_embeddings", False):
            fixed = size  # its position table was learned for that size alone (CogVideoX-5b-I2V)
    elif name == "LTXImageToVideoPipeline":
        vae, tr = config("vae"), config("transformer")
        scaling = sum(bool(s) for s in vae.get("spatio_temporal_scaling", (True, True, True, False)))
        spatial = vae.get("spatial_compression_ratio") or int(vae.get("patch_size", 4)) * 2 ** scaling
        temp = vae.get("temporal_compression_ratio") or int(vae.get("patch_size_t", 1)) * 2 ** scaling
        # the pipeline itself refuses sizes that are not multiples of 32
        multiple = math.lcm(32, int(spatial) * int(tr.get("patch_size", 1)))
        temporal = int(temp) * int(tr.get("patch_size_t", 1))
    else:  # pragma: no cover - KINDS and this function list the same classes
        raise ValueError(name)
    if multiple < 1 or temporal < 1:
        raise ValueError("non-positive scale factor")
    assert frames is not None and size is not None
    return Rules(multiple, temporal, fixed, frames, size, fps)


def call_arguments(kind: Kind, *, frames: int, steps: int, fps: float, guidance: float | None,
                   prompt: str | None, negative_prompt: str | None, motion_bucket: int | None,
                   noise_aug: float | None, decode_chunk: int) -> dict:
    """The keyword arguments of the pipeline's __call__ beyond the image, size and generator."""
    out: dict = {"num_frames": frames, "num_inference_steps": steps, "output_type": "np"}
    if kind.class_name == "StableVideoDiffusionPipeline":
        out.update(motion_bucket_id=motion_bucket, noise_aug_strength=noise_aug,
                   decode_chunk_size=min(decode_chunk, frames))
    else:
        out.update(prompt=prompt, negative_prompt=negative_prompt, guidance_scale=guidance)
    if kind.class_name == "LTXImageToVideoPipeline":
        out["frame_rate"] = int(round(fps))  # LTX-Video is conditioned on the frame rate
    return out


def frame_counts_near(frames: int, temporal: int) -> tuple[int, int]:
    """The valid frame counts (1 + k * temporal, at least 1 + temporal) just below and above `frames`."""
    low = max(1 + temporal, (frames - 1) // temporal * temporal + 1)
    high = max(1 + temporal, -(-(frames - 1) // temporal) * temporal + 1)
    return low, high
