"""slamkit: offline monocular visual SLAM with COLMAP's machinery, step by step.

>>> import slamkit
>>> slam = slamkit.Slam(slamkit.open_source("default"), slamkit.SlamConfig())   # doctest: +SKIP
>>> for result in slam: print(result)                                           # doctest: +SKIP
>>> slam.save("runs/demo")                                                      # doctest: +SKIP
"""

import sys as _sys

_modules = list(_sys.modules)
_first_pycolmap = next((k for k, m in enumerate(_modules) if m.split(".")[0] == "pycolmap"), None)
if _first_pycolmap is not None and ("numpy" not in _modules or _first_pycolmap < _modules.index("numpy")):
    # measured with pycolmap 4.2.1 (its wheel's libraries), numpy 2 and numba: after `import pycolmap` comes before
    # numpy's first import, the first numba kernel compiled in the process corrupts the heap and the process
    # aborts (SIGABRT, "malloc assertion failure" / "double free or corruption", no Python traceback), at
    # whatever frame a kernel first compiles; importing numpy first (as slamkit does) avoids it
    raise ImportError("slamkit: pycolmap was imported before numpy; with pycolmap 4.2's wheels that makes numba's "
                      "compiler (slamkit's matching and pose kernels) abort the process. Import slamkit (or numpy) "
                      "before pycolmap, e.g. move `import slamkit` above `import pycolmap`.")
del _modules, _first_pycolmap

from .interrupt import quiet_startup_interrupt as _quiet_startup_interrupt

_quiet_startup_interrupt()  # the `slamkit` command: Ctrl-C while the imports below run is one line, not a traceback

from .camera import Intrinsics
from .config import PRESETS, SlamConfig
from .errors import (AssociationError, CalibrationError, ConfigError, FormatError, ImageReadError, OutputError,
                     SlamkitError, SourceError)
from .eval import ate, evaluate, rpe
from .exporter import export
from .features import available_extractors, register_extractor
from .io import read_kitti, read_trajectory, read_tum, write_kitti, write_tum
from .pipeline import Slam, StepResult
from .sources import open_source
from .types import Frame, Trajectory

__version__ = "0.1.0"

__all__ = [
    "Slam", "SlamConfig", "StepResult", "PRESETS", "open_source", "Frame", "Trajectory", "Intrinsics",
    "ate", "rpe", "evaluate", "read_tum", "write_tum", "read_kitti", "write_kitti", "read_trajectory",
    "available_extractors", "register_extractor",
    "SlamkitError", "SourceError", "ImageReadError", "FormatError", "CalibrationError", "AssociationError",
    "ConfigError", "OutputError", "__version__",
]
__all__.append("export")
