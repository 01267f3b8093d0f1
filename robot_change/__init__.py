"""robot_change: notice when the room in front of a robot is no longer the room it remembers.

depth -> point cloud -> voxel grid -> outlier removal -> plane removal -> Gaussian mixture
(split-EM stopped by MDL) -> registration to the station's reference -> free-space check,
novelty components and EMD -> what appeared, what disappeared, where.

The public API is what this package's face names (``__all__``); it stays stable while modules
move underneath::

    from hw import open_depth
    from robot_change import build_scene, detect_changes

Names are imported on first use, so ``import robot_change`` stays light (the numba kernels
load with the first call that needs them).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

from robot_change.errors import (  # noqa: E402 -- after __version__, which modules read
    ConfigError,
    InputError,
    ProtocolError,
    RobotChangeError,
)

#: public name -> the module that defines it (the one place that knows where things live)
_API = {
    "CameraMount": "robot_change.change.mount",
    "ChangeParams": "robot_change.change.params",
    "ChangeSet": "robot_change.change.results",
    "CloudParams": "robot_change.cloud.chain",
    "Mixture": "robot_change.mixture.model",
    "Registration": "robot_change.change.registration",
    "RegistrationParams": "robot_change.change.registration",
    "SceneModel": "robot_change.change.scene",
    "SceneParams": "robot_change.change.scene",
    "build_scene": "robot_change.change.scene",
    "clean_cloud": "robot_change.cloud.chain",
    "detect_changes": "robot_change.change.detect",
    "emd": "robot_change.change.transport",
    "fit_mixture": "robot_change.mixture.model",
    "register_depth": "robot_change.change.registration",
}

# a list display (not sorted(...)) so that linters see the re-exported names; sorted in place
__all__ = [*_API, "ConfigError", "InputError", "ProtocolError", "RobotChangeError", "__version__"]
__all__.sort()


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'robot_change' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # once found, an ordinary attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
