"""Wan 2.1 video prior through diffusers: LoRA fine-tuning and SDEdit refinement.

The base model is read from a local folder in diffusers' layout (for example a copy
of ``Wan-AI/Wan2.1-T2V-1.3B-Diffusers``: ``model_index.json``, ``transformer/``,
``vae/``, ``text_encoder/``, ``tokenizer/``, ``scheduler/``) named by the ``weights``
parameter (config ``prior.wan_weights``). Weights are never downloaded: a missing
folder is an error that says so.

* Fine-tuning: a rank-32 LoRA (peft; AdamW, lr 1e-4) on the transformer's attention
  projections, trained by flow matching in the VAE's latent space on windows of
  the campaign's monocular clips, with captions from the config.
* Refinement: ``WanVideoToVideoPipeline`` whose ``strength`` is SDEdit (starting noise
  level: :func:`surfphase.prior.sdedit.flow_match_start_sigma`). Grey frames are
  repeated to RGB and back; the working size is the video's own size rounded up to a
  multiple of 16 (or ``height`` × ``width``), frames are resized to it and back.
  Wan's VAE needs 4k + 1 frames: a video is refined in chunks of ``frames`` = 4k + 1
  frames overlapping by ``overlap`` (cross-faded), and a short video is padded by
  repeating its last frame.

Captions are encoded here (tokenizer + UMT5 encoder, zeroed past each caption's
length as the pipeline does) and handed to the pipeline as ``prompt_embeds``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from surfphase.io import atomic_write_json
from surfphase.prior.interface import check_video
from surfphase.prior.sdedit import check_strength, img2img_steps, refine_in_chunks

LORA_FILE = "pytorch_lora_weights.safetensors"

DEFAULT_PARAMS: dict = {
    "weights": None,  # local folder of Wan 2.1 diffusers weights (required)
    "caption": (
        "high-speed shadowgraph video of vapour bubbles rising from a heated surface "
        "in boiling water, grayscale, dark bubble rims on a bright background"
    ),
    "captions": {},  # clip name → caption, overrides "caption" for that clip
    "negative_prompt": "",
    "lora_rank": 32,
    "lora_alpha": 32,
    "lr": 1e-4,
    "steps": 500,  # LoRA optimiser steps
    "frames": 33,  # chunk length, 4k + 1 frames
    "overlap": 8,  # frames shared by consecutive chunks
    "height": None,  # working size, pixels, multiple of 16 (None: the video's, rounded up)
    "width": None,
    "num_inference_steps": 30,
    "guidance_scale": 5.0,
    "max_sequence_length": 512,
    "dtype": "float32",  # or bfloat16 (transformer and text encoder; the VAE stays float32)
    "seed": 0,
}


def _ceil16(n: int) -> int:
    return 16 * math.ceil(n / 16)


def check_weights_folder(weights) -> Path:
    """Return the Wan weights folder, or raise FileNotFoundError explaining what to put there."""
    if not weights:
        raise FileNotFoundError(
            "wan prior: no weights folder configured (params 'weights', config "
            "prior.wan_weights). Wan 2.1 weights cannot be downloaded here: copy "
            "Wan-AI/Wan2.1-T2V-1.3B-Diffusers (diffusers layout) into a local folder"
        )
    folder = Path(weights)
    if not (folder / "model_index.json").is_file():
        raise FileNotFoundError(
            f"wan prior: weights folder {folder} not found or has no model_index.json. "
            "Wan 2.1 weights cannot be downloaded here: copy Wan-AI/Wan2.1-T2V-1.3B-Diffusers "
            "(diffusers layout) into that folder, or use --backend embedded"
        )
    return folder


def encode_captions(pipe, captions: list[str], max_sequence_length: int) -> torch.Tensor:
    """UMT5 embeddings of ``captions``: (B, max_sequence_length, text_dim), zero past each caption."""
    tok = pipe.tokenizer(
        [" ".join(c.split()) for c in captions],
        padding="max_length",
        max_length=max_sequence_length,
        truncation=True,
        add_special_tokens=True,
        return_attention_mask=True,
        return_tensors="pt",
    )
    device = pipe.text_encoder.device
    mask = tok.attention_mask.to(device)
    with torch.no_grad():
        emb = pipe.text_encoder(tok.input_ids.to(device), mask).last_hidden_state
    return emb * mask[..., None].to(emb.dtype)


WAN_PACKAGES = ("diffusers", "peft", "transformers", "accelerate")


class MissingExtraError(ValueError):
    """An optional dependency group (a pip extra) is not installed."""


def require_wan_packages() -> None:
    """Raise :class:`MissingExtraError` naming the extra when Wan's packages are missing."""
    import importlib.util

    missing = [m for m in WAN_PACKAGES if importlib.util.find_spec(m) is None]
    if missing:
        raise MissingExtraError(
            f"prior: backend: wan needs the packages {', '.join(missing)}, which are not "
            "installed: pip install 'surfphase[wan]' (or use prior: backend: embedded)"
        )


class WanPrior:
    """Wan 2.1 (diffusers) behind the :class:`~surfphase.prior.interface.VideoPrior` interface.

    Args:
        params: overrides of :data:`DEFAULT_PARAMS`; ``weights`` is required.
        device: torch device.
        lora: a folder holding ``pytorch_lora_weights.safetensors`` to load.
    """

    backend = "wan"

    def __init__(self, params: dict | None = None, device="cpu", lora: Path | None = None):
        require_wan_packages()
        from diffusers import WanVideoToVideoPipeline

        unknown = set(params or {}) - set(DEFAULT_PARAMS)
        if unknown:
            raise ValueError(f"wan prior: unknown parameters {sorted(unknown)}")
        self.params = {**DEFAULT_PARAMS, **(params or {})}
        if (int(self.params["frames"]) - 1) % 4 or int(self.params["frames"]) < 1:
            raise ValueError(f"wan prior: 'frames' must be 4k + 1, got {self.params['frames']}")
        for key in ("height", "width"):
            if self.params[key] is not None and int(self.params[key]) % 16:
                raise ValueError(f"wan prior: '{key}' must be a multiple of 16")
        folder = check_weights_folder(self.params["weights"])
        self.params["weights"] = str(folder.resolve())
        self.device = torch.device(device)
        dtype = getattr(torch, str(self.params["dtype"]))
        self.pipe = WanVideoToVideoPipeline.from_pretrained(str(folder), dtype=dtype)
        if dtype != torch.float32:  # the VAE stays in float32
            self.pipe.vae.to(torch.float32)
        self.pipe.to(self.device)
        self.pipe.set_progress_bar_config(disable=True)
        self.has_lora = False
        if lora is not None:
            self.pipe.load_lora_weights(str(lora), weight_name=LORA_FILE, adapter_name="default")
            self.has_lora = True

    # ----------------------------------------------------------- helpers
    def _work_size(self, h: int, w: int) -> tuple[int, int]:
        p = self.params
        return int(p["height"] or _ceil16(h)), int(p["width"] or _ceil16(w))

    @staticmethod
    def _resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """Resize (..., H, W) frames bilinearly (no-op when already that size)."""
        if tuple(x.shape[-2:]) == tuple(size):
            return x
        lead = x.shape[:-2]
        y = F.interpolate(x.reshape(-1, 1, *x.shape[-2:]), size=size, mode="bilinear")
        return y.reshape(*lead, *size)

    def _embed(self, captions: list[str]) -> torch.Tensor:
        emb = encode_captions(self.pipe, captions, int(self.params["max_sequence_length"]))
        return emb.to(self.pipe.transformer.dtype)

    def _latents(self, clip_window: torch.Tensor) -> torch.Tensor:
        """Normalised VAE latents of a (F, H, W) window in [0, 1] → (1, z, f, h, w)."""
        vae = self.pipe.vae
        x = (clip_window * 2 - 1)[None, None].expand(1, 3, *clip_window.shape).to(self.device)
        with torch.no_grad():
            z = vae.encode(x.to(vae.dtype)).latent_dist.mode()
        mean = torch.tensor(vae.config.latents_mean).view(1, -1, 1, 1, 1).to(z)
        std = torch.tensor(vae.config.latents_std).view(1, -1, 1, 1, 1).to(z)
        return (z - mean) / std

    # ---------------------------------------------------------- training
    def train(
        self,
        clips: list[np.ndarray],
        params: dict | None = None,
        log=print,
        names: list[str] | None = None,
    ) -> dict:
        """LoRA fine-tuning on (T_i, H_i, W_i) [0, 1] clips by flow matching; returns a log.

        Each step takes a random window of 4k + 1 frames (``frames``, or the longest
        4k + 1 that fits the clip) of a random clip, at the working size.
        """
        from peft import LoraConfig

        if params:
            unknown = set(params) - set(DEFAULT_PARAMS)
            if unknown:
                raise ValueError(f"wan prior: unknown parameters {sorted(unknown)}")
            self.params.update({k: v for k, v in params.items() if k != "weights"})
        p = self.params
        if not clips:
            raise ValueError("wan prior: no training clips")
        names = names or [f"clip{k:03d}" for k in range(len(clips))]
        for k, c in enumerate(clips):
            check_video(c, f"clip {names[k]}")
        tr = self.pipe.transformer
        if not self.has_lora:
            tr.add_adapter(
                LoraConfig(
                    r=int(p["lora_rank"]),
                    lora_alpha=int(p["lora_alpha"]),
                    init_lora_weights=True,
                    target_modules=["to_q", "to_k", "to_v", "to_out.0"],
                )
            )
            self.has_lora = True
        for name, q in tr.named_parameters():  # only the LoRA weights train
            q.requires_grad_("lora_" in name)
        trainable = [q for q in tr.parameters() if q.requires_grad]
        for q in trainable:  # LoRA weights train in float32 even on a bfloat16 base
            q.data = q.data.float()
        opt = torch.optim.AdamW(trainable, lr=float(p["lr"]))
        caps = [p["captions"].get(n, p["caption"]) for n in names]
        embeds = {c: self._embed([c]) for c in set(caps)}
        rng = np.random.default_rng([int(p["seed"]), 78])
        gen = torch.Generator().manual_seed(int(p["seed"]))
        tr.train()
        losses, t0 = [], time.perf_counter()
        steps = int(p["steps"])
        for step in range(steps):
            k = int(rng.integers(len(clips)))
            clip = clips[k]
            n = min(int(p["frames"]), 4 * ((clip.shape[0] - 1) // 4) + 1)
            a = int(rng.integers(clip.shape[0] - n + 1))
            window = torch.from_numpy(np.ascontiguousarray(clip[a : a + n], np.float32))
            window = self._resize(window, self._work_size(*clip.shape[1:]))
            z0 = self._latents(window)
            noise = torch.randn(z0.shape, generator=gen).to(z0)
            sigma = torch.rand(1, generator=gen).to(z0)
            zt = (1 - sigma) * z0 + sigma * noise
            pred = tr(
                hidden_states=zt.to(tr.dtype),
                timestep=sigma * 1000.0,
                encoder_hidden_states=embeds[caps[k]],
                return_dict=False,
            )[0]
            loss = F.mse_loss(pred.float(), (noise - z0).float())
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            if log and ((step + 1) % 10 == 0 or step + 1 == steps):
                log(f"step {step + 1}/{steps} loss {np.mean(losses[-10:]):.4f}")
        tr.eval()
        return {
            "steps": steps,
            "seconds": round(time.perf_counter() - t0, 2),
            "losses": [round(v, 5) for v in losses],
        }

    # ---------------------------------------------------------- refinement
    def _run_pipe(self, window: np.ndarray, strength: float, seed: int) -> np.ndarray:
        """One pipeline call on a (4k + 1, H, W) [0, 1] window; returns (4k + 1, H, W)."""
        p = self.params
        h, w = window.shape[1:]
        hw = self._work_size(h, w)
        x = self._resize(torch.from_numpy(np.ascontiguousarray(window, np.float32)), hw)
        rgb = x[..., None].expand(*x.shape, 3).numpy()[None]  # (1, F, H, W, 3)
        guidance = float(p["guidance_scale"])
        neg = self._embed([p["negative_prompt"]]) if guidance > 1.0 else None
        out = self.pipe(
            video=rgb,
            prompt_embeds=self._embed([p["caption"]]),
            negative_prompt_embeds=neg,
            height=hw[0],
            width=hw[1],
            num_inference_steps=int(p["num_inference_steps"]),
            guidance_scale=guidance,
            strength=strength,
            generator=torch.Generator().manual_seed(int(seed)),
            output_type="np",
        ).frames[0]
        grey = torch.from_numpy(np.asarray(out, np.float32).mean(-1))
        return self._resize(grey, (h, w)).numpy()

    def refine(self, video: np.ndarray, strength: float, seed: int = 0) -> np.ndarray:
        """SDEdit ``video`` (T, H, W) [0, 1] with Wan at ``strength``; returns (T, H, W).

        Returns the input unchanged when the strength runs no step
        (⌊num_inference_steps · strength⌋ = 0, strength 0 included).
        """
        check_video(video, "video")
        s = check_strength(strength)
        video = np.asarray(video, np.float32)
        if img2img_steps(s, int(self.params["num_inference_steps"]))[1] == 0:
            return video.copy()
        chunk = int(self.params["frames"])

        def run(window: np.ndarray, k: int) -> np.ndarray:
            t = window.shape[0]
            n = 4 * math.ceil((t - 1) / 4) + 1
            padded = np.concatenate([window, np.repeat(window[-1:], n - t, 0)]) if n > t else window
            return self._run_pipe(padded, s, seed + k)[:t]

        out = refine_in_chunks(video, chunk, int(self.params["overlap"]), run)
        return np.clip(out, 0.0, 1.0).astype(np.float32)

    def sample(self, n: int, frames: int, size: int, seed: int = 0) -> np.ndarray:
        """(n, frames, size, size) videos from pure noise (strength 1 from a grey video)."""
        grey = np.full((frames, size, size), 0.5, np.float32)
        return np.stack([self.refine(grey, 1.0, seed + 1000 * k) for k in range(n)])

    # ---------------------------------------------------------- save / load
    def save(self, folder: str | Path) -> None:
        """Write the LoRA weights (if trained) and ``prior.json`` (with the base folder)."""
        from diffusers import WanVideoToVideoPipeline
        from peft.utils import get_peft_model_state_dict

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        if self.has_lora:
            state = get_peft_model_state_dict(self.pipe.transformer)
            tmp = folder / ".lora.part"
            WanVideoToVideoPipeline.save_lora_weights(
                str(tmp), transformer_lora_layers=state, weight_name=LORA_FILE
            )
            (tmp / LORA_FILE).replace(folder / LORA_FILE)
            tmp.rmdir()
        atomic_write_json(
            folder / "prior.json",
            {"backend": self.backend, "params": self.params, "lora": self.has_lora},
        )

    @classmethod
    def load(cls, folder: str | Path, device="cpu") -> WanPrior:
        """Read a prior written by :meth:`save` (the base weights folder must still exist)."""
        folder = Path(folder)
        meta = json.loads((folder / "prior.json").read_text())
        lora = None
        if meta.get("lora"):
            if not (folder / LORA_FILE).is_file():
                raise FileNotFoundError(f"wan prior: LoRA weights {folder / LORA_FILE} not found")
            lora = folder
        return cls(meta["params"], device=device, lora=lora)
