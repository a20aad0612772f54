"""The registry of dataset loaders: every on-disk layout sync4d reads is one `Loader` entry of
`BUILTIN` (its name, title, the files that mark it, where its reader is, the test splits it
offers, its row of the docs), listed once, in detection order, like nerfstudio's table of
dataparsers. `load_scene` (sync4d.data.detect) reads a folder with the first loader that
`recognises` it. Generated from the registry: the error for a folder no loader recognises, the
config's `test_split` choices (`offered_splits`), the layouts named in `sync4d fit --help` and
the layout table of docs/datasets.md (`scripts/gen_docs.py`).

The shared preamble lives here too (`prepare`): the folder must exist and not be a file, the
test split must be one the loader offers, the resolution scale in (0, 1]. It runs once, whether
a folder is loaded through `load_scene` or a loader's own function (`load_blender`, ...); a
reader receives checked arguments.

Adding a loader takes two edits: its module, sync4d/data/<name>.py, with a
`read(root, resolution_scale, test_split) -> Scene` (JSON through `scene.read_json`, errors as
`DatasetError`), and its `Loader(...)` entry in `BUILTIN` at its place in the detection order
(a layout whose marker files another layout's folders can also hold goes first); then
`python scripts/gen_docs.py` rewrites the docs. Tests add one for a while with `register` and
remove it with `unregister`.

This module imports no loader module, nor numpy: readers are named "module:function" and
imported on first use, so `sync4d --help` can name the layouts and stay fast.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import import_module
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sync4d.data.scene import Scene

#: A reader: (checked dataset folder, resolution scale, test split) -> Scene.
Reader = Callable[[Path, float, str], "Scene"]


@dataclass(frozen=True)
class LoaderDoc:
    """A loader's row of the layout table in docs/datasets.md (Markdown)."""

    #: Where images, cameras and times come from.
    frames: str = ""
    #: What the test split is.
    test_split: str = ""
    #: Where instance masks come from ("none" when the layout has none).
    masks: str = ""


@dataclass(frozen=True)
class Loader:
    """One dataset layout."""

    #: Identifier, unique in the registry.
    name: str
    #: The layout as messages and help name it.
    title: str
    #: Files, or folders ending in "/", that mark the layout: a folder holding all of them is
    #: recognised unless `detect` decides instead.
    markers: tuple[str, ...]
    #: The reader, or "module:function" naming it (imported on first use).
    read: str | Reader
    #: Recognises a folder by something other than all of `markers` existing.
    detect: Callable[[Path], bool] | None = None
    #: The test splits the reader offers, "test" first.
    test_splits: tuple[str, ...] = ("test",)
    #: Said after the title where the layouts are listed.
    note: str = ""
    doc: LoaderDoc = field(default_factory=LoaderDoc)

    def recognises(self, root: Path) -> bool:
        """Whether folder `root` is in this layout."""
        if self.detect is not None:
            return self.detect(root)
        return all((root / m.rstrip("/")).exists() for m in self.markers)

    def reader(self) -> Reader:
        """The reader function, imported if `read` names it."""
        if not isinstance(self.read, str):
            return self.read
        module, _, function = self.read.partition(":")
        return getattr(import_module(module), function)

    def expects(self) -> str:
        """Markers and title as the unrecognised-layout error lists them."""
        note = f", {self.note}" if self.note else ""
        return f"{' + '.join(self.markers)} ({self.title}{note})"

    def load(
        self, root: str | Path, resolution_scale: float = 1.0, test_split: str = "test"
    ) -> Scene:
        """Read dataset folder `root` in this layout, after the shared checks (`prepare`).
        Headers are not checked: `load_scene` does that (`check_scene`)."""
        path, _ = prepare(root, resolution_scale, test_split, self)
        return self.reader()(path, resolution_scale, test_split)


def _colmap_folder(root: Path) -> bool:
    # sparse/ alone picks COLMAP, whose loader then says that images/ is missing.
    return (root / "sparse").exists()


#: Every loader sync4d ships, in detection order (the first that recognises a folder reads it).
BUILTIN: tuple[Loader, ...] = (
    Loader(
        name="blender",
        title="D-NeRF/Blender",
        markers=("transforms_train.json",),
        read="sync4d.data.blender:read",
        test_splits=("test", "val"),
        doc=LoaderDoc(
            frames="`transforms_{train,val,test}.json`: `camera_angle_x`, per frame "
            "`file_path`, `time`, OpenGL camera-to-world `transform_matrix`",
            test_split='`transforms_test.json` (`transforms_val.json` with `test_split = "val"`)',
            masks="`masks/{split}/<name>.png` (indexed labels), names in `masks/labels.json`",
        ),
    ),
    Loader(
        name="panoptic",
        title="Dynamic-3DGS Panoptic",
        markers=("train_meta.json",),
        read="sync4d.data.panoptic:read",
        doc=LoaderDoc(
            frames="`train_meta.json` / `test_meta.json`: `w`, `h`, per time and camera "
            "intrinsics `k` and OpenCV `w2c`, image paths `fn` under `ims/`",
            test_split="`test_meta.json`",
            masks='binary foreground masks `seg/<cam>/<frame>.png` (label 1 "foreground")',
        ),
    ),
    Loader(
        name="hypernerf",
        title="HyperNeRF",
        markers=("dataset.json", "metadata.json"),
        read="sync4d.data.hypernerf:read",
        doc=LoaderDoc(
            frames="`camera/<id>.json` (Nerfies cameras), images `rgb/{1x,2x,...}/<id>.png` "
            "(the finest folder there is when the asked one is missing), time from "
            "`metadata.json` (`time_id`, or `warp_id`); `scene.json` `center` and `scale` "
            "normalise camera centres and points as HyperNeRF does; points `points.npy`",
            test_split="`val_ids` of `dataset.json`",
            masks="`masks/<id>.png`, names in `masks/labels.json`",
        ),
    ),
    Loader(
        name="nerfstudio",
        title="nerfstudio",
        markers=("transforms.json",),
        read="sync4d.data.nerfstudio:read",
        note="e.g. from sync4d process",
        doc=LoaderDoc(
            frames="`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` (top level or per frame), OpenGL "
            "`transform_matrix`, per-frame `time` (without any: the frames sorted by file "
            "name, evenly spaced), lens distortion `k1`..`k4`, `p1`, `p2` (undistorted on "
            "load), points `ply_file_path`",
            test_split="`test_filenames` when present, else every 8th frame in the file's order",
            masks="per-frame `mask_path`",
        ),
    ),
    Loader(
        name="colmap",
        title="COLMAP",
        markers=("sparse/", "images/"),
        read="sync4d.data.colmap:read",
        detect=_colmap_folder,
        doc=LoaderDoc(
            frames="the sparse model in `sparse/0/` or `sparse/` (`.bin` or `.txt`, read with "
            "pycolmap); time from `times.json` (image name -> time), else the images sorted "
            "by name as one video",
            test_split="`test_images.txt` (one name per line), else every 8th image",
            masks="`masks/<image stem>.png`, names in `masks/labels.json`",
        ),
    ),
)

_registry: list[Loader] = []


def register(loader: Loader, *, before: str | None = None) -> None:
    """Add `loader` to the detection order: last, or just before the loader called `before`.
    Its name must be new."""
    if loader.name in names():
        raise ValueError(f"a dataset loader called {loader.name!r} is already registered")
    index = len(_registry) if before is None else _registry.index(get(before))
    _registry.insert(index, loader)


def unregister(name: str) -> Loader:
    """Remove the loader called `name` (e.g. one a test registered) and return it."""
    loader = get(name)
    _registry.remove(loader)
    return loader


def loaders() -> tuple[Loader, ...]:
    """Every registered loader, in detection order."""
    return tuple(_registry)


def names() -> tuple[str, ...]:
    """The registered loaders' names, in detection order."""
    return tuple(loader.name for loader in _registry)


def get(name: str) -> Loader:
    """The loader called `name`, else `KeyError` listing the names."""
    for loader in _registry:
        if loader.name == name:
            return loader
    raise KeyError(f"no dataset loader {name!r}; loaders: {', '.join(names())}")


def offered_splits() -> tuple[str, ...]:
    """Every test split some loader offers, in registry order ("test" first)."""
    out: list[str] = []
    for loader in _registry:
        out += [s for s in loader.test_splits if s not in out]
    return tuple(out)


def titles() -> str:
    """The loaders' titles in detection order, for help text: "A, B, C or D"."""
    return _or([loader.title for loader in _registry])


def _or(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def detect(root: Path) -> Loader:
    """The first loader that recognises folder `root`, else `DatasetError` listing what each
    layout expects."""
    from sync4d.data.scene import DatasetError

    for loader in _registry:
        if loader.recognises(root):
            return loader
    expected = _or([loader.expects() for loader in _registry])
    raise DatasetError(root, f"unrecognised dataset layout: expected {expected}")


def prepare(
    root: str | Path, resolution_scale: float, test_split: str, loader: Loader | None = None
) -> tuple[Path, Loader]:
    """The checks every load starts with, run once: `root` must be an existing folder (a file
    gets the `sync4d process` hint), `loader` (detected when None) must offer `test_split`,
    and `resolution_scale` must be in (0, 1]. Returns `root` as a Path and the loader."""
    from sync4d.data.scene import DatasetError

    root = Path(root)
    if root.is_file():
        raise DatasetError(
            root, "is a file, not a dataset folder; for a video (or a folder of photos) make a "
            f"dataset first: sync4d process {root} --out DATA, then sync4d fit DATA",
        )  # fmt: skip
    if not root.is_dir():
        raise DatasetError(root, "dataset directory does not exist")
    if loader is None:
        loader = detect(root)
    if test_split not in loader.test_splits:
        offering = [lo.title for lo in _registry if test_split in lo.test_splits]
        where = f"only available for {_or(offering)} datasets" if offering else "not available"
        raise DatasetError(root, f"test split '{test_split}' is {where}")
    if not (0.0 < resolution_scale <= 1.0):
        raise DatasetError(root, f"resolution scale must be in (0, 1], got {resolution_scale}")
    return root, loader


for _loader in BUILTIN:
    register(_loader)
del _loader
