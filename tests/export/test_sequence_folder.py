"""The 4D export as a folder of PLYs that SuperSplat imports as a sequence (issue 53).

The naming convention is checked against SuperSplat's own reader, read at
playcanvas/supersplat cc6e86a (2026-07-21):

* ``src/file-handler.ts`` ``isPlySequence(filenames)``: the dropped or picked files (names
  lower-cased) are a PLY sequence when there are at least two and every one matches
  ``/(.*?)(\\d+)(?:\\.compressed)?\\.ply$/`` with the same group 1 (the prefix before the
  trailing frame number) as the first; otherwise each file is imported on its own (a ``.json``
  among them is read as camera poses). A dropped folder is expanded to all its files
  (``src/drop-handler.ts`` ``resolveDirectories``), so the folder must hold the frames alone.
* ``src/sequence.ts`` ``PlyFrameSource``: frames are played in the order of
  ``parseInt(group 2)``.

`supersplat_sequence_order` below restates those two functions; the old zip members
(``frame_0000_t0.0000.ply``) fail it (their prefixes differ by the time), the folder's names
pass it in frame order. Each frame is a standard 3DGS PLY read with plyfile.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData

from sync4d.cli import main
from sync4d.export import (
    ExportError,
    is_sequence_folder,
    ply_properties,
    read_ply,
    read_sequence,
    sequence_frame_name,
    sequence_sidecar,
    splats_at,
    write_sequence,
    write_sequence_folder,
)
from sync4d.phase1.gaussians import DeformableGaussians

#: SuperSplat's pattern (src/file-handler.ts isPlySequence, src/sequence.ts PlyFrameSource).
SUPERSPLAT_FRAME = re.compile(r"(.*?)(\d+)(?:\.compressed)?\.ply$")


def supersplat_sequence_order(filenames: list[str]) -> list[str] | None:
    """The files in the order SuperSplat plays them when it takes them as one PLY sequence,
    None when it imports them one by one (isPlySequence false)."""
    names = [f.lower() for f in filenames]
    if len(names) < 2:
        return None
    matches = [SUPERSPLAT_FRAME.search(n) for n in names]
    if any(m is None for m in matches) or len({m[1] for m in matches}) != 1:
        return None
    order = sorted(range(len(names)), key=lambda i: int(matches[i][2]))
    return [filenames[i] for i in order]


def test_the_convention_rejects_the_old_zip_names_and_stray_files() -> None:
    old = [f"frame_{i:04d}_t{t:.4f}.ply" for i, t in enumerate((0.0, 0.25, 0.5))]
    assert supersplat_sequence_order(old) is None  # prefixes "frame_0000_t0." ... differ
    ok = ["bb_0002.ply", "bb_0000.ply", "bb_0010.ply", "bb_0001.ply"]
    assert supersplat_sequence_order(ok) == ["bb_0000.ply", "bb_0001.ply", "bb_0002.ply",
                                             "bb_0010.ply"]  # fmt: skip
    assert supersplat_sequence_order([*ok, "bb.json"]) is None
    assert supersplat_sequence_order(["bb_0000.ply"]) is None  # one file: a plain import


@pytest.fixture(scope="module")
def model() -> DeformableGaussians:
    gen = torch.Generator().manual_seed(3)
    m = DeformableGaussians(torch.rand(40, 3, generator=gen) - 0.5, torch.rand(40, 3,
                                                                                 generator=gen),
                            generator=gen)  # fmt: skip
    with torch.no_grad():
        m.deform.head.weight.normal_(0.0, 0.5, generator=gen)
    return m


@pytest.mark.parametrize("folder_name", ["bb-4d", "run 2.v1", "scene7"])
def test_folder_names_follow_supersplat_and_frames_are_standard_plys(
    model: DeformableGaussians, tmp_path: Path, folder_name: str
) -> None:
    times = np.linspace(0.0, 1.0, 12)
    labels = np.arange(model.num_gaussians) % 3
    folder = write_sequence_folder(tmp_path / folder_name, model, times, labels)
    names = sorted(p.name for p in folder.iterdir())
    assert len(names) == 12
    order = supersplat_sequence_order(names)
    assert order is not None, names
    assert order == [sequence_frame_name(folder, i) for i in range(12)]
    assert all(re.fullmatch(r"[A-Za-z0-9_-]+_\d{4}\.ply", n) for n in names)
    side = json.loads(sequence_sidecar(folder).read_text())
    assert sequence_sidecar(folder).parent == folder.parent  # beside the folder, not in it
    assert [f["file"] for f in side["frames"]] == order
    assert [f["time"] for f in side["frames"]] == pytest.approx(times.tolist())
    k = model.sh_rest.shape[1]
    for i, name in enumerate(order):
        ply = PlyData.read(str(folder / name))
        assert [el.name for el in ply.elements] == ["vertex"]
        vertex = ply["vertex"]
        props = [p.name for p in vertex.properties]
        assert props[: len(ply_properties(k))] == ply_properties(k)
        assert all(vertex.data[p].dtype == np.dtype("<f4") for p in ply_properties(k))
        assert not ply.text and ply.byte_order == "<" and len(vertex.data) == 40
        want = splats_at(model, float(times[i]), labels)
        got = read_ply(folder / name)
        assert got.time == pytest.approx(times[i])
        np.testing.assert_array_equal(got.means, want.means)
        np.testing.assert_array_equal(got.object_ids, labels)
    t, frames = read_sequence(folder)
    assert t == pytest.approx(times) and len(frames) == 12


def test_folder_rewrites_its_frames_and_refuses_foreign_files(
    model: DeformableGaussians, tmp_path: Path
) -> None:
    folder = tmp_path / "seq"
    write_sequence_folder(folder, model, np.linspace(0, 1, 5))
    write_sequence_folder(folder, model, np.linspace(0, 1, 3))  # shorter: stale frames go
    assert sorted(p.name for p in folder.iterdir()) == [f"seq_{i:04d}.ply" for i in range(3)]
    (folder / "notes.txt").write_text("x")
    with pytest.raises(ExportError, match="holds other files"):
        write_sequence_folder(folder, model, [0.0, 1.0])
    with pytest.raises(ExportError, match="not a frame"):
        read_sequence(folder)
    file = tmp_path / "file"
    file.write_text("x")
    with pytest.raises(ExportError, match="not a folder"):
        write_sequence_folder(file, model, [0.0, 1.0])


def test_which_paths_are_folders(tmp_path: Path) -> None:
    assert is_sequence_folder("out/bb-4d/") and is_sequence_folder("bb-4d")
    assert not is_sequence_folder("bb.ply") and not is_sequence_folder("bb.zip")
    (tmp_path / "x.ply").mkdir()
    assert is_sequence_folder(tmp_path / "x.ply")


def test_write_sequence_dispatches_a_folder(model: DeformableGaussians, tmp_path: Path) -> None:
    out = write_sequence(str(tmp_path / "d") + "/", model, [0.0, 0.5, 1.0])
    assert out.is_dir() and len(list(out.iterdir())) == 3
    with pytest.raises(ValueError, match="folder"):
        write_sequence(tmp_path / "bad.txt", model, [0.0])


def test_export_command_writes_the_folder(tmp_path: Path, capsys) -> None:
    from support.datasets import write_blender

    write_blender(tmp_path / "tiny", n=4, size=16)
    assert main(["fit", str(tmp_path / "tiny"), "--out", str(tmp_path / "run"), "--iters", "4",
                 "--threads", "1", "--phases", "1", "--set", "phase1.init_points=100",
                 "--set", "eval_every=0"]) == 0  # fmt: skip
    capsys.readouterr()
    folder = tmp_path / "out" / "bb-4d"
    assert main(["export", str(tmp_path / "run"), "--sequence", f"{folder}/", "--frames", "4",
                 "--threads", "1"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "bb-4d_0000.ply" in printed and "4 frames" in printed and "bb-4d.json" in printed
    names = sorted(p.name for p in folder.iterdir())
    assert supersplat_sequence_order(names) == [f"bb-4d_{i:04d}.ply" for i in range(4)]
    assert main(["export", str(tmp_path / "run"), "--sequence", str(tmp_path / "s.zip"),
                 "--frames", "2", "--threads", "1"]) == 0  # fmt: skip
    out, err = capsys.readouterr()
    assert "s.zip (2 frames)" in out and "deprecated" in err and "DIR/" in err
