"""Segment Anything (SAM, MobileSAM and compatible) through ONNX Runtime.

Two ONNX files, as written by segment-anything's ``scripts/export_onnx_model.py`` or
by samexporter:

* the **image encoder**: one input, either (1, 3, 1024, 1024) float32 — the image
  resized so its longest side is 1024, normalised with SAM's pixel mean/std and
  zero-padded at the bottom/right — or (h', w', 3) float32 RGB in 0..255 already
  resized, when the export embedded the normalisation and padding
  (samexporter ``--use-preprocess``); one output ``image_embeddings`` (1, 256, 64, 64);
* the **prompt decoder** (``SamOnnxModel``): inputs ``image_embeddings``,
  ``point_coords`` (B, P, 2) float32 in the 1024-resized frame, ``point_labels``
  (B, P) float32 (1 foreground, 0 background, −1 padding), ``mask_input``
  (B, 1, 256, 256), ``has_mask_input`` (B,), ``orig_im_size`` (2,) float32 [H, W];
  outputs ``masks`` (B, K, H, W) logits, ``iou_predictions`` (B, K) and
  ``low_res_masks`` (B, K, 256, 256). K is 4 (single-mask token then three
  multimask tokens) or 1 with ``--return-single-mask``.

The exported decoders fix the batch dimension to 1; prompts are then decoded one
at a time, and in batches when the file allows a dynamic batch. The image is
encoded once per frame. Masks are rebuilt from ``low_res_masks`` with SAM's own
post-processing (upsample to 1024², crop the padding, resize to the image), which
stays right for every aspect ratio even where an export froze the crop size.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F

from surfphase.masks import amg
from surfphase.masks.classical import to_unit_float
from surfphase.masks.params import SAM_DEFAULTS

#: SAM's input side and its RGB normalisation (pixel values 0..255).
SAM_IMAGE_SIZE = 1024
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], np.float32)
PIXEL_STD = np.array([58.395, 57.12, 57.375], np.float32)

DECODER_INPUTS = (
    "image_embeddings",
    "point_coords",
    "point_labels",
    "mask_input",
    "has_mask_input",
    "orig_im_size",
)

_HOW_TO_EXPORT = (
    "export the model with segment-anything's scripts/export_onnx_model.py "
    "(or samexporter's export_encoder/export_decoder) and put the files there"
)


def resized_shape(height: int, width: int, long_side: int = SAM_IMAGE_SIZE) -> tuple[int, int]:
    """(h', w') of an image resized so its longest side is ``long_side`` (SAM's rounding)."""
    scale = long_side / max(height, width)
    return int(height * scale + 0.5), int(width * scale + 0.5)


def to_sam_coords(uv: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixel coordinates (N, 2) of the original image → SAM's 1024-resized frame.

    SAM (``ResizeLongestSide.apply_coords``) scales x by w'/W and y by h'/H; the
    decoder then adds 0.5 to reach pixel centres, so integer inputs are pixel
    indices, as in this project's convention.
    """
    h2, w2 = resized_shape(height, width)
    out = np.asarray(uv, np.float64).copy()
    out[..., 0] *= w2 / width
    out[..., 1] *= h2 / height
    return out.astype(np.float32)


@functools.lru_cache(maxsize=16)
def resample_matrix(n_low: int, n_crop: int, n_out: int) -> np.ndarray:
    """(n_out, n_low) matrix of SAM's 1-D mask post-processing along one axis.

    Linear (``align_corners=False``) resampling of ``n_low`` samples to
    ``SAM_IMAGE_SIZE``, keeping the first ``n_crop``, then linear resampling to
    ``n_out``; built by pushing the identity through the same torch operations.
    """
    eye = torch.eye(n_low, dtype=torch.float64).unsqueeze(1)  # (n_low, 1, n_low)
    up = F.interpolate(eye, size=SAM_IMAGE_SIZE, mode="linear", align_corners=False)
    out = F.interpolate(up[..., :n_crop], size=n_out, mode="linear", align_corners=False)
    return out[:, 0, :].T.numpy().astype(np.float32)


def _session(path: Path, what: str, key: str) -> ort.InferenceSession:
    if not path.is_file():
        raise FileNotFoundError(
            f"SAM {what} model not found: {path} (config key masks.sam.{key}); {_HOW_TO_EXPORT}"
        )
    try:
        return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(
            f"SAM {what} model {path} (masks.sam.{key}) is not a readable ONNX model: {e}"
        ) from e


class SamOnnx:
    """An ONNX SAM model: encoder and prompt decoder sessions, checked on load.

    Args:
        encoder: path of the image-encoder ``.onnx`` file.
        decoder: path of the prompt-decoder ``.onnx`` file.

    Raises FileNotFoundError when a file is missing and ValueError when it is not a
    readable ONNX model or lacks SAM's inputs and outputs.
    """

    def __init__(self, encoder: str | os.PathLike, decoder: str | os.PathLike) -> None:
        self.encoder_path = Path(encoder)
        self.decoder_path = Path(decoder)
        self.encoder = _session(self.encoder_path, "encoder", "encoder")
        self.decoder = _session(self.decoder_path, "decoder", "decoder")
        enc_in = self.encoder.get_inputs()
        if len(enc_in) != 1 or len(enc_in[0].shape) not in (3, 4):
            raise ValueError(
                f"{self.encoder_path}: expected a SAM image encoder with one input of rank 3 "
                f"(H, W, 3) or 4 (1, 3, 1024, 1024), got "
                f"{[(i.name, i.shape) for i in enc_in]}"
            )
        self.encoder_input = enc_in[0].name
        self.encoder_rank = len(enc_in[0].shape)
        self.encoder_input_shape = enc_in[0].shape
        enc_out = [o.name for o in self.encoder.get_outputs()]
        self.encoder_output = "image_embeddings" if "image_embeddings" in enc_out else enc_out[0]
        dec_in = {i.name: i for i in self.decoder.get_inputs()}
        missing = [n for n in DECODER_INPUTS if n not in dec_in]
        dec_out = [o.name for o in self.decoder.get_outputs()]
        if (
            missing
            or "iou_predictions" not in dec_out
            or not ("low_res_masks" in dec_out or "masks" in dec_out)
        ):
            raise ValueError(
                f"{self.decoder_path}: not a SAM prompt decoder (inputs {sorted(dec_in)}, "
                f"outputs {dec_out}); expected inputs {list(DECODER_INPUTS)} and outputs "
                "masks, iou_predictions, low_res_masks"
            )
        self.decoder_outputs = dec_out
        b = dec_in["point_coords"].shape[0]
        # A symbolic or missing batch size means prompts can be decoded together.
        self.dynamic_batch = not isinstance(b, int)
        emb = dec_in["image_embeddings"].shape
        self.embedding_shape = tuple(d if isinstance(d, int) else None for d in emb)
        mi = dec_in["mask_input"].shape
        self.mask_input_hw = tuple(d if isinstance(d, int) else 256 for d in mi[-2:])

    # -- encoder -------------------------------------------------------------

    def preprocess(self, image: np.ndarray) -> np.ndarray:
        """(H, W) or (H, W, 3) image → the encoder's input array.

        Grey frames are repeated into RGB 0..255, resized (bilinear) so the longest
        side is 1024; for rank-4 encoders also normalised, made CHW and padded.
        """
        img = np.asarray(image)
        if (
            img.ndim not in (2, 3)
            or min(img.shape[:2]) < 1
            or (img.ndim == 3 and img.shape[2] != 3)
        ):
            raise ValueError(f"expected a (H, W) or (H, W, 3) image, got shape {img.shape}")
        if img.ndim == 2:
            rgb = np.repeat(to_unit_float(img)[:, :, None], 3, axis=2)
        elif np.issubdtype(img.dtype, np.integer):
            rgb = img.astype(np.float32) / float(np.iinfo(img.dtype).max)
        else:
            rgb = np.clip(img.astype(np.float32), 0, 1)
        h, w = rgb.shape[:2]
        h2, w2 = resized_shape(h, w)
        t = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))[None] * 255.0
        t = F.interpolate(t, size=(h2, w2), mode="bilinear", align_corners=False, antialias=True)
        resized = t[0].permute(1, 2, 0).numpy()
        if self.encoder_rank == 3:
            return np.ascontiguousarray(resized, np.float32)
        x = (resized - PIXEL_MEAN) / PIXEL_STD
        out = np.zeros((1, 3, SAM_IMAGE_SIZE, SAM_IMAGE_SIZE), np.float32)
        out[0, :, :h2, :w2] = x.transpose(2, 0, 1)
        want = self.encoder_input_shape
        if all(isinstance(d, int) for d in want[1:]) and tuple(want[1:]) != out.shape[1:]:
            raise ValueError(
                f"{self.encoder_path}: encoder input has shape {want}; SAM encoders take "
                f"(1, 3, {SAM_IMAGE_SIZE}, {SAM_IMAGE_SIZE})"
            )
        return out

    def embed(self, image: np.ndarray) -> np.ndarray:
        """Run the encoder once on a frame → (1, C, 64, 64) float32 image embeddings."""
        x = self.preprocess(image)
        try:
            (emb,) = self.encoder.run([self.encoder_output], {self.encoder_input: x})
        except Exception as e:
            raise ValueError(
                f"{self.encoder_path}: the encoder failed on a {x.shape} input: {e}"
            ) from e
        want = self.embedding_shape
        if emb.ndim != 4 or any(
            d is not None and d != g for d, g in zip(want[1:], emb.shape[1:], strict=True)
        ):
            raise ValueError(
                f"{self.encoder_path}: encoder output has shape {emb.shape}, the decoder "
                f"{self.decoder_path} expects image_embeddings of shape {want}"
            )
        return emb.astype(np.float32)

    # -- decoder -------------------------------------------------------------

    def _decode(
        self,
        embedding: np.ndarray,
        coords: np.ndarray,
        labels: np.ndarray,
        orig_hw: tuple[int, int],
    ) -> tuple[np.ndarray, np.ndarray]:
        b = coords.shape[0]
        feeds = {
            "image_embeddings": embedding,
            "point_coords": coords.astype(np.float32),
            "point_labels": labels.astype(np.float32),
            "mask_input": np.zeros((b, 1, *self.mask_input_hw), np.float32),
            "has_mask_input": np.zeros(b, np.float32),
            "orig_im_size": np.asarray(orig_hw, np.float32),
        }
        names = [
            "low_res_masks" if "low_res_masks" in self.decoder_outputs else "masks",
            "iou_predictions",
        ]
        try:
            masks, iou = self.decoder.run(names, feeds)
        except Exception as e:
            raise ValueError(f"{self.decoder_path}: the decoder failed: {e}") from e
        return masks, iou

    def upscale_low_res(self, low_res: np.ndarray, orig_hw: tuple[int, int]) -> np.ndarray:
        """(B, K, h, w) low-resolution logits → (B, K, H, W) logits at the image size.

        SAM's post-processing: bilinear to 1024×1024, crop the padding to the resized
        image (h', w'), bilinear to (H, W). Bilinear resampling is separable and
        linear, so the chain is applied as two small matrices per axis
        (:func:`resample_matrix`), without the 1024² intermediate.
        """
        h, w = orig_hw
        h2, w2 = resized_shape(h, w)
        mr = resample_matrix(low_res.shape[-2], h2, h)
        mc = resample_matrix(low_res.shape[-1], w2, w)
        b, k, hl, wl = low_res.shape
        # Two plain 2-D products (BLAS), columns first, then rows.
        cols = np.ascontiguousarray(low_res, np.float32).reshape(-1, wl) @ mc.T  # (BKhl, W)
        cols = cols.reshape(b * k, hl, w).transpose(1, 0, 2).reshape(hl, -1)
        out = (mr @ cols).reshape(h, b * k, w).transpose(1, 0, 2)
        return np.ascontiguousarray(out.reshape(b, k, h, w))

    def predict_points(
        self,
        embedding: np.ndarray,
        points: np.ndarray,
        orig_hw: tuple[int, int],
        batch: int = 64,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Decode one foreground point prompt per row of ``points``.

        Args:
            embedding: (1, C, 64, 64) from :meth:`embed`.
            points: (N, 2) pixel coordinates (u, v) in the original image.
            orig_hw: (H, W) of the original image.
            batch: prompts per decoder call when the decoder's batch is dynamic.

        Returns:
            logits: (N, K, H, W) float32 mask logits (threshold 0);
            iou: (N, K) float32 predicted IoU.
        """
        h, w = orig_hw
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        # SAM's prompt without a box: the point, then a padding point (0, 0) labelled −1.
        coords = np.zeros((pts.shape[0], 2, 2), np.float32)
        coords[:, 0] = to_sam_coords(pts, h, w)
        labels = np.tile(np.array([1.0, -1.0], np.float32), (pts.shape[0], 1))
        step = max(1, int(batch)) if self.dynamic_batch else 1
        outs, ious = [], []
        for i in range(0, pts.shape[0], step):
            m, q = self._decode(embedding, coords[i : i + step], labels[i : i + step], (h, w))
            if m.shape[-2:] != (h, w):
                m = self.upscale_low_res(m, (h, w))
            outs.append(m)
            ious.append(q)
        if not outs:
            return np.zeros((0, 1, h, w), np.float32), np.zeros((0, 1), np.float32)
        return np.concatenate(outs).astype(np.float32), np.concatenate(ious).astype(np.float32)

    # -- automatic mask generation ------------------------------------------------

    def generate(
        self, image: np.ndarray, params: Mapping | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Automatic masks of one frame → ((H, W) int32 labels, −1 background; (n,) scores).

        The encoder runs once; a ``points_per_side``² grid of prompts is decoded in
        batches of ``points_per_batch``, each batch filtered (predicted IoU,
        stability) before the next, then NMS and small-region removal as in SAM.
        """
        p = {**SAM_DEFAULTS, **(params or {})}
        img = np.asarray(image)
        h, w = img.shape[:2]
        emb = self.embed(img)
        grid = amg.point_grid(int(p["points_per_side"]), w, h)
        masks, scores = [], []
        nb = max(1, int(p["points_per_batch"]))
        for i in range(0, grid.shape[0], nb):
            logits, iou = self.predict_points(emb, grid[i : i + nb], (h, w), batch=nb)
            if logits.shape[1] > 1:
                # Multimask tokens 1..3, as SAM's automatic generator uses.
                logits, iou = logits[:, 1:], iou[:, 1:]
            m, s = amg.filter_candidates(
                logits.reshape(-1, h, w),
                iou.reshape(-1),
                float(p["pred_iou_thresh"]),
                float(p["stability_score_thresh"]),
                stability_offset=float(p["stability_score_offset"]),
            )
            masks.append(m)
            scores.append(s)
        all_m = np.concatenate(masks) if masks else np.zeros((0, h, w), bool)
        all_s = np.concatenate(scores) if scores else np.zeros(0)
        all_m, all_s = amg.postprocess_masks(
            all_m, all_s, float(p["box_nms_thresh"]), int(p["min_region_area"])
        )
        return amg.masks_to_labels(all_m, all_s)


def load_sam(params: Mapping, base_dir: str | os.PathLike | None = None) -> SamOnnx:
    """Build :class:`SamOnnx` from ``masks.sam`` parameters (paths relative to ``base_dir``)."""
    p = {**SAM_DEFAULTS, **params}
    paths = []
    for key in ("encoder", "decoder"):
        if not p.get(key):
            raise ValueError(f"config key masks.sam.{key} is empty; {_HOW_TO_EXPORT}")
        path = Path(p[key])
        if base_dir is not None and not path.is_absolute():
            path = Path(base_dir) / path
        paths.append(path)
    return SamOnnx(*paths)
