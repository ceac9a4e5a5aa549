"""The Wan 2.1 path with a tiny randomly initialised Wan built here (no download)."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch

from surfphase.cli import main
from surfphase.prior import load_prior
from surfphase.prior.sdedit import flow_match_start_sigma
from surfphase.prior.wan import WanPrior, check_weights_folder

# Looked up, not imported: diffusers and peft take about 7 s to import, which every
# pytest-xdist worker would pay at collection, not only the one that runs these tests.
pytestmark = pytest.mark.skipif(
    not all(importlib.util.find_spec(m) for m in ("diffusers", "peft")),
    reason="the 'wan' extra (diffusers, peft) is not installed",
)

WORDS = ("<pad> </s> <unk> high-speed shadowgraph video of vapour bubbles rising from a "
         "heated surface in boiling water, grayscale dark rims on bright background")  # fmt: skip
PARAMS = {"frames": 9, "overlap": 4, "num_inference_steps": 4, "max_sequence_length": 16,
          "guidance_scale": 2.0, "steps": 2}  # fmt: skip


def build_tiny_wan(folder) -> None:
    """Save a tiny random Wan 2.1 pipeline (diffusers' test-sized dims) in ``folder``.

    The text encoder is a tiny UMT5 from a config and the tokenizer a word-level
    ``tokenizers`` vocabulary, so nothing is downloaded.
    """
    from diffusers import (
        AutoencoderKLWan,
        FlowMatchEulerDiscreteScheduler,
        WanTransformer3DModel,
        WanVideoToVideoPipeline,
    )
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, UMT5Config, UMT5EncoderModel

    torch.manual_seed(0)
    vae = AutoencoderKLWan(base_dim=3, z_dim=16, dim_mult=[1, 1, 1, 1], num_res_blocks=1,
                           temperal_downsample=[False, True, True])  # fmt: skip
    transformer = WanTransformer3DModel(
        patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=12, in_channels=16,
        out_channels=16, text_dim=32, freq_dim=256, ffn_dim=32, num_layers=2,
        cross_attn_norm=True, qk_norm="rms_norm_across_heads", rope_max_seq_len=32,
    )  # fmt: skip
    text_encoder = UMT5EncoderModel(
        UMT5Config(
            vocab_size=64,
            d_model=32,
            d_kv=8,
            d_ff=37,
            num_layers=2,
            num_heads=4,
            relative_attention_num_buckets=8,
        )  # fmt: skip
    )
    vocab = {w: i for i, w in enumerate(dict.fromkeys(WORDS.split()))}
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=tok, pad_token="<pad>", eos_token="</s>", unk_token="<unk>"
    )
    pipe = WanVideoToVideoPipeline(
        tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer,
        scheduler=FlowMatchEulerDiscreteScheduler(shift=7.0),
    )  # fmt: skip
    pipe.save_pretrained(folder)


def clip(seed: int, frames: int = 10, h: int = 16, w: int = 16) -> np.ndarray:
    return np.random.default_rng(seed).random((frames, h, w)).astype(np.float32)


@pytest.fixture(scope="module")
def wan(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("wan")
    build_tiny_wan(root / "weights")
    prior = WanPrior(dict(PARAMS, weights=str(root / "weights")))
    log = prior.train([clip(0), clip(1)], log=None, names=["a", "b"])
    prior.save(root / "prior")
    return prior, log, root


def test_missing_weights_say_they_cannot_be_downloaded(tmp_path):
    with pytest.raises(FileNotFoundError, match="cannot be downloaded"):
        check_weights_folder(tmp_path / "Wan2.1-T2V-1.3B-Diffusers")
    with pytest.raises(FileNotFoundError, match="no weights folder configured"):
        WanPrior({})
    with pytest.raises(ValueError, match="4k"):
        WanPrior({"frames": 8, "weights": str(tmp_path)})


def test_lora_training_saves_and_reloads(wan):
    from peft.utils import get_peft_model_state_dict

    prior, log, root = wan
    assert log["steps"] == 2 and all(np.isfinite(log["losses"]))
    assert (root / "prior" / "pytorch_lora_weights.safetensors").is_file()
    meta = json.loads((root / "prior" / "prior.json").read_text())
    assert meta["backend"] == "wan" and meta["lora"] and meta["params"]["lora_rank"] == 32
    trained = get_peft_model_state_dict(prior.pipe.transformer)
    loaded = get_peft_model_state_dict(load_prior(root / "prior").pipe.transformer)
    assert len(trained) > 0 and trained.keys() == loaded.keys()
    assert any(k.endswith("lora_A.weight") and v.shape[0] == 32 for k, v in trained.items())
    for k in trained:
        torch.testing.assert_close(loaded[k], trained[k])
    # AdamW moved the zero-initialised lora_B weights
    assert any(float(v.abs().max()) > 0 for k, v in trained.items() if "lora_B" in k)


def test_refine_runs_chunked_and_is_deterministic(wan):
    prior, _, root = wan
    video = clip(7, frames=13, h=16, w=24)
    a = prior.refine(video, 0.5, seed=3)
    b = load_prior(root / "prior").refine(video, 0.5, seed=3)
    assert a.shape == video.shape and a.dtype == np.float32
    assert 0.0 <= a.min() and a.max() <= 1.0 and np.array_equal(a, b)
    assert not np.array_equal(a, video)


def test_strength_zero_returns_input(wan):
    prior, _, _ = wan
    video = clip(8, frames=5)
    assert np.array_equal(prior.refine(video, 0.0, seed=0), video)
    # ⌊4 steps · 0.2⌋ = 0 steps: the pipeline would run nothing, so the input comes back
    assert np.array_equal(prior.refine(video, 0.2, seed=0), video)


@pytest.mark.parametrize("strength", [0.5, 0.75])
def test_wan_starts_at_documented_noise_level(wan, strength):
    prior, _, _ = wan
    seen = []

    def hook(_mod, _args, kwargs):
        seen.append(float(kwargs["timestep"].flatten()[0]))

    handle = prior.pipe.transformer.register_forward_pre_hook(hook, with_kwargs=True)
    try:
        prior.refine(clip(9, frames=5), strength, seed=0)
    finally:
        handle.remove()
    n = PARAMS["num_inference_steps"]
    sigma = flow_match_start_sigma(strength, n, shift=7.0)
    assert seen[0] / 1000 == pytest.approx(sigma, abs=1e-5)
    assert len(seen) == 2 * int(n * strength)  # guidance 2: conditional + unconditional


def test_train_prior_command_with_wan(wan, tmp_path):
    import cv2

    _, _, root = wan
    for k in range(2):
        d = tmp_path / "clips" / f"clip{k}"
        d.mkdir(parents=True)
        for f, frame in enumerate(clip(20 + k, frames=9)):
            cv2.imwrite(str(d / f"{f:06d}.png"), np.round(frame * 255).astype(np.uint8))
    params = dict(PARAMS, weights=str(root / "weights"), steps=1, num_inference_steps=2)
    out = tmp_path / "prior"
    assert main(["train-prior", "--backend", "wan", "--clips", str(tmp_path / "clips"),
                 "--out", str(out), "--threads", "1", "--samples", "1",
                 "--params-json", json.dumps(params)]) == 0  # fmt: skip
    names = {p.name for p in out.iterdir()}
    assert {"prior.json", "pytorch_lora_weights.safetensors", "samples.png", "train.json"} <= names


def test_missing_wan_packages_name_the_extra(monkeypatch):
    """Without diffusers/peft the backend says which packages and which extra to install."""
    import importlib.util

    from surfphase.prior import wan

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda m, *a: None if m in ("diffusers", "peft") else real(m)
    )
    with pytest.raises(wan.MissingExtraError, match=r"diffusers, peft.*surfphase\[wan\]"):
        wan.WanPrior({"weights": "nowhere"})
