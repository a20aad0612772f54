"""`DeformableGaussians.render(..., threads=T)` runs every Rust op on T threads: the spherical
harmonics too, which ran on rayon's default pool (all cores) before (issue 51)."""

from __future__ import annotations

import pytest

from support.scenes import orbit_camera, random_gaussians
from sync4d import raster

OPS = ("sh_forward", "sh_backward", "project_forward", "project_backward")


def test_render_passes_its_threads_to_every_op(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[tuple[str, int]] = []
    for name in OPS:
        op = getattr(raster._core, name)

        def spy(*args, _name=name, _op=op, **kwargs):
            # threads: by name, or the op's last positional argument
            seen.append((_name, kwargs["threads"] if "threads" in kwargs else args[-1]))
            return _op(*args, **kwargs)

        monkeypatch.setattr(raster._core, name, spy)
    model = random_gaussians(30, 0, sh_degree=3)
    model.render(orbit_camera(0.5), 0.4, threads=1).features.sum().backward()
    assert {name for name, _ in seen} == set(OPS)
    assert all(threads == 1 for _, threads in seen), seen
