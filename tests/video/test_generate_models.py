"""`pdtool generate` on the image-to-video pipelines beyond SVD: Wan 2.x, CogVideoX and
LTX-Video image-to-video, each a tiny randomly initialised pipeline of the real diffusers /
transformers classes built here from its config (under 0.5 MB, no download); the size and
length rules read from their configs; and the settings that belong to one kind of model."""
from __future__ import annotations

import importlib.util
import inspect
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cli import main

pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.skipif(
    not all(importlib.util.find_spec(m) for m in ("diffusers", "transformers", "ftfy", "sentencepiece")),
    reason='needs the video extra: pip install -e ".[video]"')]

SIZE = ["--width", "64", "--height", "32"]  # multiples of 32 (LTX-Video's pipeline asks that of every model)
FAST = ["--frames", "5", "--steps", "2"]  # 1 + 4k frames: the tiny VAEs compress time 4x


def _tokenizer():
    """A word-level tokenizer with T5's special tokens, saved as tokenizer.json (no pickle)."""
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    words = "<pad> </s> <unk> the a object plant sways gently after light push then settles static camera".split()
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    return PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="<pad>", eos_token="</s>", unk_token="<unk>")


def _text_encoder(umt5: bool = False):
    from transformers import T5Config, T5EncoderModel, UMT5Config, UMT5EncoderModel

    cfg = dict(vocab_size=32, d_model=16, d_kv=4, d_ff=16, num_layers=1, num_heads=2, relative_attention_num_buckets=8)
    return UMT5EncoderModel(UMT5Config(**cfg)) if umt5 else T5EncoderModel(T5Config(**cfg))


def build_tiny_wan(folder: Path) -> Path:
    """WanImageToVideoPipeline (Wan 2.1's layout: UMT5 text encoder, CLIP image encoder)."""
    from diffusers import AutoencoderKLWan, FlowMatchEulerDiscreteScheduler, WanImageToVideoPipeline, WanTransformer3DModel
    from transformers import CLIPImageProcessor, CLIPVisionConfig, CLIPVisionModel

    torch.manual_seed(0)
    # 4 VAE levels: 8x in space, 4x in time; the transformer's 2 px patches make frames multiples of 16
    vae = AutoencoderKLWan(base_dim=8, z_dim=4, dim_mult=[1, 1, 1, 1], num_res_blocks=1,
                           temperal_downsample=[False, True, True], latents_mean=[0.0] * 4, latents_std=[1.0] * 4)
    # input channels: 4 of noise, 4 of the image's latents, 4 of the first-frame mask (the VAE's time factor)
    transformer = WanTransformer3DModel(patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=8, in_channels=12,
                                        out_channels=4, text_dim=16, freq_dim=32, ffn_dim=16, num_layers=1, image_dim=8,
                                        rope_max_seq_len=32)
    encoder = CLIPVisionModel(CLIPVisionConfig(hidden_size=8, num_hidden_layers=2, num_attention_heads=2, image_size=32,
                                               intermediate_size=16, patch_size=8))
    WanImageToVideoPipeline(tokenizer=_tokenizer(), text_encoder=_text_encoder(umt5=True), vae=vae,
                            scheduler=FlowMatchEulerDiscreteScheduler(shift=3.0),
                            image_processor=CLIPImageProcessor(crop_size=32, size=32), image_encoder=encoder,
                            transformer=transformer).save_pretrained(folder)
    return folder


def build_tiny_cogvideox(folder: Path) -> Path:
    """CogVideoXImageToVideoPipeline with learned positional embeddings, as CogVideoX-5b-I2V:
    it takes its configured size (64 x 32 here) and no other."""
    from diffusers import (AutoencoderKLCogVideoX, CogVideoXDDIMScheduler, CogVideoXImageToVideoPipeline,
                           CogVideoXTransformer3DModel)

    torch.manual_seed(0)
    vae = AutoencoderKLCogVideoX(block_out_channels=(8, 8, 8), down_block_types=("CogVideoXDownBlock3D",) * 3,
                                 up_block_types=("CogVideoXUpBlock3D",) * 3, latent_channels=4, layers_per_block=1,
                                 norm_num_groups=2, temporal_compression_ratio=4, sample_height=32, sample_width=64)
    # sample size in latents (4x below the frames); head dim 16 so that rotary splits it evenly; the
    # position table also covers the prompt's 226 tokens, the pipeline's default length
    transformer = CogVideoXTransformer3DModel(
        num_attention_heads=2, attention_head_dim=16, in_channels=8, out_channels=4, time_embed_dim=8, text_embed_dim=16,
        num_layers=1, sample_width=16, sample_height=8, sample_frames=9, patch_size=2, temporal_compression_ratio=4,
        max_text_seq_length=226, use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
    CogVideoXImageToVideoPipeline(tokenizer=_tokenizer(), text_encoder=_text_encoder(), vae=vae, transformer=transformer,
                                  scheduler=CogVideoXDDIMScheduler()).save_pretrained(folder)
    return folder


def build_tiny_ltx(folder: Path) -> Path:
    from diffusers import (AutoencoderKLLTXVideo, FlowMatchEulerDiscreteScheduler, LTXImageToVideoPipeline,
                           LTXVideoTransformer3DModel)

    torch.manual_seed(0)
    vae = AutoencoderKLLTXVideo(latent_channels=8, block_out_channels=(8, 8, 8, 8), decoder_block_out_channels=(8, 8, 8, 8),
                                layers_per_block=(1, 1, 1, 1, 1), decoder_layers_per_block=(1, 1, 1, 1, 1),
                                spatio_temporal_scaling=(True, True, False, False),
                                decoder_spatio_temporal_scaling=(True, True, False, False),
                                decoder_inject_noise=(False,) * 5, upsample_residual=(False,) * 4, upsample_factor=(1,) * 4,
                                patch_size=1, patch_size_t=1)
    transformer = LTXVideoTransformer3DModel(in_channels=8, out_channels=8, num_attention_heads=2, attention_head_dim=8,
                                             cross_attention_dim=16, num_layers=1, caption_channels=16)
    LTXImageToVideoPipeline(scheduler=FlowMatchEulerDiscreteScheduler(), vae=vae, text_encoder=_text_encoder(),
                            tokenizer=_tokenizer(), transformer=transformer).save_pretrained(folder)
    return folder


BUILDERS = {"WanImageToVideoPipeline": build_tiny_wan, "CogVideoXImageToVideoPipeline": build_tiny_cogvideox,
            "LTXImageToVideoPipeline": build_tiny_ltx}
FPS = {"WanImageToVideoPipeline": 16.0, "CogVideoXImageToVideoPipeline": 8.0, "LTXImageToVideoPipeline": 25.0}


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("i2v")
    return {name: build(base / name) for name, build in BUILDERS.items()}


def run_cli(*args):
    return CliRunner().invoke(main, ["generate", *[str(a) for a in args]])


@pytest.mark.parametrize("name", list(BUILDERS))
def test_each_pipeline_makes_a_video_folder_that_fit_reads(name: str, tiny_models, shared_data: Path,
                                                           tmp_path: Path) -> None:
    from pd_tool.core.cameras import load_cameras
    from pd_tool.video.folder import load_reference_video
    from pd_tool.video.models import DEFAULT_PROMPT

    out = tmp_path / "video"
    res = run_cli(shared_data / "udon.ply", "--up", "-y", "--model", tiny_models[name], *SIZE, *FAST, "--count", "2",
                  "-o", out)
    assert res.exit_code == 0, res.output
    for k in range(2):
        frames = sorted((out / f"video_{k}").glob("frame_*.png"))
        assert len(frames) == 5
        ref = load_reference_video(out / f"video_{k}", working_size=None)
        assert tuple(ref.frames.shape) == (5, 32, 64, 3) and ref.fps == FPS[name]  # the model's own frame rate
        assert load_cameras(out / f"video_{k}" / "camera.json")[0].fps == FPS[name]
    record = json.loads((out / "generate.json").read_text())
    assert record["pipeline"] == name and record["settings"]["prompt"] == DEFAULT_PROMPT
    assert record["settings"]["motion_bucket"] is None and record["settings"]["guidance"] > 0
    assert [v["seed"] for v in record["videos"]] == [0, 1]
    assert (out / "contact_sheet.png").is_file() and "camera motion" in res.stdout
    # two seeds, two videos (the prompt and the seed reach the model)
    a = load_reference_video(out / "video_0", working_size=None).frames
    b = load_reference_video(out / "video_1", working_size=None).frames
    assert float((a - b).abs().max()) > 0.01


def test_a_model_of_fixed_size_makes_its_size_by_default_and_refuses_another(tiny_models, shared_data: Path,
                                                                            tmp_path: Path) -> None:
    cog = tiny_models["CogVideoXImageToVideoPipeline"]
    out = tmp_path / "video"
    res = run_cli(shared_data / "udon.ply", "--up", "-y", "--model", cog, "--steps", "1", "-o", out)
    assert res.exit_code == 0, res.output
    frames = sorted(out.glob("frame_*.png"))
    assert len(frames) == 9  # the transformer's sample_frames, the model's own length
    from pd_tool.video.folder import load_reference_video

    assert tuple(load_reference_video(out, working_size=None).frames.shape) == (9, 32, 64, 3)
    res = run_cli(shared_data / "udon.ply", "--model", cog, "--width", "96", "--height", "32", "-o", tmp_path / "b")
    assert res.exit_code == 2 and "64x32 frames only" in res.stderr and "--width 64 --height 32" in res.stderr
    assert not (tmp_path / "b").exists()


def test_settings_of_another_kind_of_model_and_bad_lengths_are_one_line(tiny_models, shared_data: Path,
                                                                        tmp_path: Path) -> None:
    from tests.video.test_generate import build_tiny_svd

    svd = build_tiny_svd(tmp_path / "svd")
    wan = tiny_models["WanImageToVideoPipeline"]
    scene = shared_data / "udon.ply"
    cases = [
        ([scene, "--model", wan, *SIZE, "--frames", "6"], "use --frames 5 or --frames 9"),
        ([scene, "--model", tiny_models["LTXImageToVideoPipeline"], *SIZE, "--frames", "4"], "--frames 5"),
        ([scene, "--model", wan, *SIZE, "--motion-bucket", "5"], "conditioned on --prompt"),
        ([scene, "--model", svd, "--width", "64", "--height", "48", "--prompt", "a plant"], "takes no text"),
        ([scene, "--model", wan, "--width", "72", "--height", "32"], "multiples of 16"),
    ]
    for args, words in cases:
        out = tmp_path / "out"
        res = run_cli(*args, "-o", out)
        assert res.exit_code == 2, (args, res.output)
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and "Traceback" not in res.output, (args, res.stderr)
        assert not out.exists()


def test_inspect_reads_each_models_rules_and_checks_its_components(tiny_models, tmp_path: Path) -> None:
    from pd_tool.video.generate import GenerateError, inspect_model

    got = {name: inspect_model(path) for name, path in tiny_models.items()}
    assert {n: (i.multiple, i.rules.temporal, i.rules.fixed_size) for n, i in got.items()} == {
        "WanImageToVideoPipeline": (16, 4, None), "CogVideoXImageToVideoPipeline": (8, 4, (64, 32)),
        "LTXImageToVideoPipeline": (32, 4, None)}
    # Wan 2.2's image-to-video download has no image encoder (null in model_index.json)
    wan22 = tmp_path / "wan22"
    shutil.copytree(tiny_models["WanImageToVideoPipeline"], wan22)
    index = json.loads((wan22 / "model_index.json").read_text())
    index["image_encoder"] = index["image_processor"] = [None, None]
    (wan22 / "model_index.json").write_text(json.dumps(index))
    shutil.rmtree(wan22 / "image_encoder")
    assert inspect_model(wan22).multiple == 16
    # a text encoder with only a pickled .bin is refused before anything loads
    pickled = tmp_path / "pickled"
    shutil.copytree(tiny_models["LTXImageToVideoPipeline"], pickled)
    for f in (pickled / "text_encoder").glob("*.safetensors"):
        f.unlink()
    (pickled / "text_encoder" / "pytorch_model.bin").write_bytes(b"\x80\x04")
    with pytest.raises(GenerateError, match="pickles that can run code"):
        inspect_model(pickled)
    missing = tmp_path / "no_tokenizer"
    shutil.copytree(tiny_models["CogVideoXImageToVideoPipeline"], missing)
    shutil.rmtree(missing / "tokenizer")
    with pytest.raises(GenerateError, match="no tokenizer/tokenizer_config.json"):
        inspect_model(missing)


def _defaults(cls_name: str) -> dict:
    """A diffusers class's __init__ defaults: the configs of the released models."""
    import diffusers

    params = inspect.signature(getattr(diffusers, cls_name).__init__).parameters.values()
    return {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}


def test_the_released_models_rules_match_their_pipelines_own_factors() -> None:
    """On diffusers' default configs (the released models'), the rules read from configs
    equal the factors each pipeline computes once loaded: Wan 16 px / 1 + 4k frames,
    CogVideoX-5b-I2V 720 x 480 only / 49 frames, LTX-Video 32 px / 1 + 8k frames."""
    from pd_tool.video.models import KINDS, rules

    wan = rules(KINDS["WanImageToVideoPipeline"],
                {"vae": _defaults("AutoencoderKLWan"), "transformer": _defaults("WanTransformer3DModel")}.get)
    assert (wan.multiple, wan.temporal, wan.size, wan.frames, wan.fps) == (16, 4, (832, 480), 81, 16.0)
    cog_tr = dict(_defaults("CogVideoXTransformer3DModel"), use_learned_positional_embeddings=True)  # 5b-I2V's
    cog = rules(KINDS["CogVideoXImageToVideoPipeline"],
                {"vae": _defaults("AutoencoderKLCogVideoX"), "transformer": cog_tr}.get)
    assert (cog.multiple, cog.temporal, cog.fixed_size, cog.frames, cog.fps) == (16, 4, (720, 480), 49, 8.0)
    cog15_tr = dict(_defaults("CogVideoXTransformer3DModel"), patch_size_t=2, sample_height=300, sample_width=300,
                    sample_frames=81)  # CogVideoX1.5-5B-I2V's transformer config
    cog15 = rules(KINDS["CogVideoXImageToVideoPipeline"],
                  {"vae": _defaults("AutoencoderKLCogVideoX"), "transformer": cog15_tr}.get)
    assert (cog15.fixed_size, cog15.size, cog15.frames, cog15.fps) == (None, (1360, 768), 81, 16.0)
    ltx = rules(KINDS["LTXImageToVideoPipeline"],
                {"vae": _defaults("AutoencoderKLLTXVideo"), "transformer": _defaults("LTXVideoTransformer3DModel")}.get)
    assert (ltx.multiple, ltx.temporal, ltx.size, ltx.frames) == (32, 8, (704, 512), 161)
    # the pipelines' own factors, from the same configs
    from diffusers import AutoencoderKLLTXVideo

    vae = AutoencoderKLLTXVideo.from_config({**_defaults("AutoencoderKLLTXVideo"), "block_out_channels": (8, 8, 8, 8),
                                             "decoder_block_out_channels": (8, 8, 8, 8)})
    assert (vae.spatial_compression_ratio, vae.temporal_compression_ratio) == (32, 8)


def test_frame_counts_near_are_valid_and_bracket_the_ask() -> None:
    from pd_tool.video.models import frame_counts_near

    for t in (1, 4, 8):
        for n in range(1 + t, 60):
            low, high = frame_counts_near(n, t)
            assert (low - 1) % t == 0 and (high - 1) % t == 0 and low <= n <= high and high - low in (0, t)
            assert (low == high) == ((n - 1) % t == 0)
    assert frame_counts_near(14, 4) == (13, 17) and frame_counts_near(17, 8) == (17, 17)
    assert frame_counts_near(3, 4) == (5, 5)  # never fewer than 1 + t


def test_a_text_model_without_its_tokeniser_packages_is_one_clean_line(tiny_models, shared_data: Path,
                                                                       tmp_path: Path) -> None:
    import subprocess
    import sys

    # a fresh interpreter in which `import ftfy` fails, as with an older video extra
    code = "import sys; sys.modules['ftfy'] = None; from cli import main; main()"
    out = tmp_path / "video"
    proc = subprocess.run([sys.executable, "-c", code, "generate", str(shared_data / "udon.ply"), "--model",
                           str(tiny_models["WanImageToVideoPipeline"]), *SIZE, "-o", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "ftfy is not importable" in lines[0] and 'pip install "pdtool[video]"' in lines[0]
    assert not out.exists()
