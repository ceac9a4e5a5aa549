"""SAM through ONNX Runtime, with tiny ONNX models built here with SAM's exact I/O.

The tiny encoder turns the (normalised, padded) 1024² input back into pixel values
and returns the local *darkness* in every channel of a 1×256×64×64 embedding. The
tiny decoder follows ``SamOnnxModel``'s conventions — points shifted by +0.5 and
divided by 1024, padding point labelled −1, ``masks`` at ``orig_im_size`` — and
returns four tokens: token 0 a disk of radius ``R[0]`` around
the prompt (to check the coordinate transforms), tokens 1–3 the dark region within
radius ``R[k]`` of the prompt, with a predicted IoU growing with the darkness at
the prompt. A correct pipeline must therefore find every dark disk.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from surfphase.masks import sam_onnx
from surfphase.masks.sam_onnx import PIXEL_MEAN, PIXEL_STD, SamOnnx, load_sam, resized_shape

torch.set_num_threads(1)

#: Token radii in the 1024-resized frame.
RADII = (64.0, 51.0, 160.0, 192.0)
DARK_LEVEL = 0.6


def _darkness(x01: torch.Tensor) -> torch.Tensor:
    """(1, 3, 1024, 1024) pixel values 0..255 → (1, 256, 64, 64) darkness in [0, 1]."""
    grey = x01.mean(dim=1, keepdim=True) / 255.0
    dark = F.avg_pool2d(1.0 - grey, 16)
    return dark.expand(1, 256, 64, 64)


class TinyEncoder(nn.Module):
    """Takes SAM's normalised, padded (1, 3, 1024, 1024) input."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(PIXEL_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(PIXEL_STD).view(1, 3, 1, 1))

    def forward(self, input_image: torch.Tensor) -> torch.Tensor:
        return _darkness(input_image * self.std + self.mean)


class TinyEncoderWithPreprocess(nn.Module):
    """Takes (h', w', 3) RGB 0..255 already resized; normalises and pads inside."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(PIXEL_MEAN))
        self.register_buffer("std", torch.tensor(PIXEL_STD))

    def forward(self, input_image: torch.Tensor) -> torch.Tensor:
        x = ((input_image - self.mean) / self.std).permute(2, 0, 1)
        h, w = x.shape[-2:]
        x = F.pad(x, (0, 1024 - w, 0, 1024 - h)).unsqueeze(0)
        return _darkness(x * self.std.view(1, 3, 1, 1) + self.mean.view(1, 3, 1, 1))


class TinyDecoder(nn.Module):
    def forward(
        self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size
    ):
        b = point_coords.shape[0]
        dark = F.interpolate(
            image_embeddings[:, :1], size=(256, 256), mode="bilinear", align_corners=False
        ).expand(b, 1, 256, 256)
        # Low-res pixel centres in the 1024 frame (continuous coordinates).
        c = (torch.arange(256, dtype=torch.float32) + 0.5) * 4.0
        pt = point_coords[:, 0] + 0.5  # as SamOnnxModel._embed_points
        d = torch.sqrt(
            (c.view(1, 1, 256) - pt[:, 0].view(b, 1, 1)) ** 2
            + (c.view(1, 256, 1) - pt[:, 1].view(b, 1, 1)) ** 2
        )
        gate = 40.0 * (dark[:, 0] - DARK_LEVEL)
        toks = [(RADII[0] - d) / 4.0]
        for r in RADII[1:]:
            toks.append(torch.minimum((r - d) / 4.0, gate))
        low = torch.stack(toks, dim=1)
        # Wiring: the padding point must be there, and no mask prompt.
        ok = (
            (point_labels[:, 1] == -1).float()
            * (1.0 - has_mask_input)
            * (point_labels[:, 0] == 1).float()
        )
        g = (pt / 1024.0) * 2 - 1
        at = F.grid_sample(dark, g.view(b, 1, 1, 2), align_corners=False).view(b)
        at = torch.clamp((at - 0.2) / 0.6, 0.0, 1.0)
        iou = torch.stack([torch.ones_like(at)] + [at * (0.9 + 0.03 * k) for k in (1, 2, 3)], 1)
        iou = iou * ok.view(b, 1) + 0.0 * mask_input.mean()
        # ``masks`` at orig_im_size, cheaply (low-res crop resized directly): the
        # pipeline rebuilds masks from ``low_res_masks`` with SAM's exact chain.
        scale = 1024.0 / torch.max(orig_im_size)
        pre = torch.floor(orig_im_size * scale / 4.0 + 0.5).to(torch.int64)
        hw = orig_im_size.to(torch.int64)
        masks = F.interpolate(
            low[..., : pre[0], : pre[1]], size=(hw[0], hw[1]), mode="bilinear", align_corners=False
        )
        return masks, iou, low


def _export(module, args, path, names, outputs, dynamic_axes=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=names,
            output_names=outputs,
            dynamic_axes=dynamic_axes,
            opset_version=17,
            dynamo=False,
        )


def build_tiny_sam(
    folder: Path, preprocess: bool = False, dynamic_batch: bool = False
) -> tuple[Path, Path]:
    """Write tiny encoder/decoder ONNX files with SAM's input and output names."""
    folder.mkdir(parents=True, exist_ok=True)
    enc = folder / ("enc_pre.onnx" if preprocess else "enc.onnx")
    if preprocess:
        _export(
            TinyEncoderWithPreprocess(),
            (torch.rand(683, 1024, 3) * 255,),
            enc,
            ["input_image"],
            ["image_embeddings"],
            {"input_image": {0: "image_height", 1: "image_width"}},
        )
    else:
        _export(
            TinyEncoder(),
            (torch.randn(1, 3, 1024, 1024),),
            enc,
            ["input_image"],
            ["image_embeddings"],
        )
    dec = folder / ("dec_batch.onnx" if dynamic_batch else "dec.onnx")
    dummy = (
        torch.rand(1, 256, 64, 64),
        torch.randint(0, 1024, (1, 5, 2)).float(),
        torch.tensor([[1.0, -1.0, 0.0, 1.0, 1.0]]),
        torch.zeros(1, 1, 256, 256),
        torch.tensor([0.0]),
        torch.tensor([1500.0, 2250.0]),
    )
    axes = {"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}}
    if dynamic_batch:
        axes = {
            "point_coords": {0: "batch", 1: "num_points"},
            "point_labels": {0: "batch", 1: "num_points"},
            "mask_input": {0: "batch"},
            "has_mask_input": {0: "batch"},
        }
    _export(
        TinyDecoder(),
        dummy,
        dec,
        list(sam_onnx.DECODER_INPUTS),
        ["masks", "iou_predictions", "low_res_masks"],
        axes,
    )
    return enc, dec


def dark_disks(h: int, w: int, disks, bg: float = 0.8, fg: float = 0.1):
    """Grey image with uniform dark disks (u, v, r) and its (H, W) int32 truth (−1 bg)."""
    vv, uu = np.mgrid[0:h, 0:w]
    img = np.full((h, w), bg, np.float32)
    truth = np.full((h, w), -1, np.int32)
    for k, (u, v, r) in enumerate(disks):
        inside = (uu - u) ** 2 + (vv - v) ** 2 <= r * r
        img[inside] = fg
        truth[inside] = k
    return img, truth


@pytest.fixture(scope="module")
def tiny_sam(tmp_path_factory):
    return build_tiny_sam(tmp_path_factory.mktemp("sam"))


def test_point_prompt_lands_where_sam_puts_it(tiny_sam):
    enc, dec = tiny_sam
    model = SamOnnx(enc, dec)
    h, w = 96, 160  # landscape: resized to 614 × 1024, padded below
    emb = model.embed(np.full((h, w), 0.8, np.float32))
    assert emb.shape == (1, 256, 64, 64)
    pts = np.array([[40.0, 30.0], [121.0, 70.0], [80.5, 48.0]])
    logits, iou = model.predict_points(emb, pts, (h, w))
    assert logits.shape == (3, 4, h, w) and iou.shape == (3, 4)
    s = resized_shape(h, w)[1] / w
    for k, (u, v) in enumerate(pts):
        m = logits[k, 0] > 0
        vv, uu = np.nonzero(m)
        # SAM's convention: the prompt's continuous position is u·s + 0.5 in the
        # resized frame, i.e. u + 0.5/s − 0.5 in pixel-centre coordinates.
        assert uu.mean() == pytest.approx(u + 0.5 / s - 0.5, abs=0.25)
        assert vv.mean() == pytest.approx(v + 0.5 / s - 0.5, abs=0.25)
        r = RADII[0] / s
        assert m.sum() == pytest.approx(np.pi * r * r, rel=0.05)


def test_encoder_with_embedded_preprocessing_gives_same_embedding(tiny_sam, tmp_path):
    enc, dec = tiny_sam
    enc_pre, _ = build_tiny_sam(tmp_path, preprocess=True)
    img, _ = dark_disks(96, 160, [(40, 50, 15)])
    a = SamOnnx(enc, dec)
    b = SamOnnx(enc_pre, dec)
    assert a.encoder_rank == 4 and b.encoder_rank == 3
    np.testing.assert_allclose(a.embed(img), b.embed(img), atol=1e-4)


def test_automatic_masks_find_every_bubble(tiny_sam):
    model = SamOnnx(*tiny_sam)
    assert not model.dynamic_batch  # as segment-anything's export: one prompt per call
    disks = [(30, 48, 14), (80, 40, 12), (130, 55, 16)]
    img, truth = dark_disks(96, 160, disks)
    labels, scores = model.generate(
        img, {"points_per_side": 10, "points_per_batch": 16, "min_region_area": 10}
    )
    assert labels.shape == img.shape and labels.dtype == np.int32
    assert labels.max() + 1 == len(disks) == len(scores)
    for k in range(len(disks)):
        t = truth == k
        ids, cnt = np.unique(labels[t], return_counts=True)
        p = labels == ids[np.argmax(cnt)]
        assert (t & p).sum() / (t | p).sum() > 0.85
    assert np.all(scores > 0.88)


def test_batched_decoder_gives_the_same_masks(tiny_sam, tmp_path):
    enc, dec = tiny_sam
    _, dec_batch = build_tiny_sam(tmp_path, dynamic_batch=True)
    one, many = SamOnnx(enc, dec), SamOnnx(enc, dec_batch)
    assert many.dynamic_batch
    img, _ = dark_disks(96, 160, [(30, 48, 14), (80, 40, 12)])
    emb = one.embed(img)
    pts = np.array([[30.0, 48.0], [80.0, 40.0], [5.0, 5.0], [150.0, 90.0], [31.0, 47.0]])
    a_logits, a_iou = one.predict_points(emb, pts, img.shape)
    b_logits, b_iou = many.predict_points(emb, pts, img.shape, batch=3)
    np.testing.assert_allclose(a_logits, b_logits, atol=1e-4)
    np.testing.assert_allclose(a_iou, b_iou, atol=1e-6)


def test_missing_model_names_key_and_export_script(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"masks\.sam\.encoder.*export_onnx_model\.py"):
        load_sam({"encoder": str(tmp_path / "none.onnx"), "decoder": str(tmp_path / "d.onnx")})


def test_corrupt_model_is_a_clear_error(tiny_sam, tmp_path):
    enc, dec = tiny_sam
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(dec.read_bytes()[:200])
    with pytest.raises(ValueError, match="broken.onnx.*not a readable ONNX model"):
        SamOnnx(enc, bad)
    # A valid ONNX file that is not a SAM decoder.
    with pytest.raises(ValueError, match="not a SAM prompt decoder"):
        SamOnnx(enc, enc)


def test_encoder_of_wrong_input_size_is_a_clear_error(tiny_sam, tmp_path):
    _, dec = tiny_sam
    small = tmp_path / "enc512.onnx"

    class Enc512(nn.Module):
        def forward(self, input_image):
            return F.avg_pool2d(input_image.mean(1, keepdim=True), 8).expand(1, 256, 64, 64)

    _export(Enc512(), (torch.randn(1, 3, 512, 512),), small, ["input_image"], ["image_embeddings"])
    model = SamOnnx(small, dec)
    with pytest.raises(ValueError, match="enc512.onnx.*1024"):
        model.embed(np.zeros((64, 64), np.float32))
    with pytest.raises(ValueError, match="shape"):
        model.embed(np.zeros((4, 5, 6), np.float32))


def test_mask_stage_runs_with_the_sam_backend(tiny_sam, tmp_path):
    """The stage, SAM backend, tiny models: every dark sphere found, ids agree."""
    import json

    from test_masks_scene import rising, write_ingest

    from surfphase.masks.stage import run_mask_stage

    enc, dec = tiny_sam
    spheres = [rising(-0.002, 0.003, 0.0, 0.002), rising(0.0025, 0.0095, 0.0, 0.002)]
    truth = write_ingest(tmp_path / "ingest", spheres, 2, size=64, core=False)
    params = {
        "backend": "sam",
        "overlay_frames": 1,
        # Small bubbles in a 64-pixel frame: their edge band is a larger share.
        "sam": {
            "encoder": str(enc),
            "decoder": str(dec),
            "points_per_side": 8,
            "min_region_area": 4,
            "stability_score_thresh": 0.85,
        },
    }
    run_mask_stage(tmp_path / "ingest", tmp_path / "out", params)
    ids = {}
    for c in truth:
        lab = np.load(tmp_path / "out" / f"{c}_labels.npy")
        assert lab.shape == truth[c].shape
        for k in range(2):
            for t in range(2):
                g = truth[c][t] == k
                v, cnt = np.unique(lab[t][g], return_counts=True)
                best = v[np.argmax(cnt)]
                p = lab[t] == best
                assert best >= 1 and (g & p).sum() / (g | p).sum() > 0.75
                ids.setdefault((c, k), set()).add(int(best))
    for k in range(2):
        assert ids[("cam0", k)] == ids[("cam1", k)] and len(ids[("cam0", k)]) == 1
    info = json.loads((tmp_path / "out" / "masks.json").read_text())
    assert info["backend"] == "sam" and info["bubbles"] == 2


def test_sam_stage_without_models_says_where_to_put_them(tmp_path):
    from test_masks_scene import rising, write_ingest

    from surfphase.masks.stage import run_mask_stage

    write_ingest(tmp_path / "ingest", [rising(0.0, 0.005, 0.0, 0.001)], 1, size=32)
    with pytest.raises(FileNotFoundError, match=r"masks\.sam\.encoder.*samexporter"):
        run_mask_stage(
            tmp_path / "ingest",
            tmp_path / "out",
            {"backend": "sam", "sam": {"encoder": str(tmp_path / "e.onnx")}},
        )
    assert not (tmp_path / "out").exists()


def test_low_res_post_processing_matches_sam_chain(tiny_sam):
    """The separable post-processing equals SAM's upsample → crop → resize in torch."""
    model = SamOnnx(*tiny_sam)
    low = np.random.default_rng(0).normal(size=(2, 4, 256, 256)).astype(np.float32)
    for h, w in ((96, 160), (130, 70), (64, 64)):
        h2, w2 = resized_shape(h, w)
        t = F.interpolate(
            torch.from_numpy(low), size=(1024, 1024), mode="bilinear", align_corners=False
        )[..., :h2, :w2]
        ref = F.interpolate(t, size=(h, w), mode="bilinear", align_corners=False).numpy()
        np.testing.assert_allclose(model.upscale_low_res(low, (h, w)), ref, atol=2e-4)
