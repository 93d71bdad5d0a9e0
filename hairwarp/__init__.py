"""hairwarp: hair simulation on NVIDIA Warp.

Guide strands are articulated rigid chains advanced by Featherstone's articulated-body
algorithm, one Warp thread per strand; they collide with bodies, hold their style with
breakable static links, repel and rub against each other on triangle strips, and drive
dense hair that is written to USD animation caches.

The public names below are imported on first use, so ``import hairwarp`` stays light for
programs that only need the step API.
"""

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    # core
    "Groom": "hairwarp.groom",
    "GroomError": "hairwarp.groom",
    "scalp_groom": "hairwarp.groom",
    "read_tfx": "hairwarp.io.tfx",
    "read_hair": "hairwarp.io.cem_hair",
    "write_hair": "hairwarp.io.cem_hair",
    "StrandParams": "hairwarp.model",
    "Model": "hairwarp.model",
    "State": "hairwarp.state",
    "Control": "hairwarp.state",
    "Solver": "hairwarp.solver",
    "SimulationFault": "hairwarp.solver",
    # enums shared with the kernels
    "Integrator": "hairwarp.kernels.types",
    "Fault": "hairwarp.kernels.types",
    "ColliderKind": "hairwarp.kernels.types",
    # colliders and interactions
    "Collider": "hairwarp.colliders",
    "ColliderSet": "hairwarp.colliders",
    "ColliderError": "hairwarp.colliders",
    "StaticLinks": "hairwarp.interactions",
    "HairContacts": "hairwarp.interactions",
    "TriangleStrips": "hairwarp.interactions",
    # dense hair and output
    "DenseHair": "hairwarp.dense",
    "CacheWriter": "hairwarp.io.cache",
    # scenes and runs
    "Scene": "hairwarp.scene",
    "SceneError": "hairwarp.scene",
    "HeadMotion": "hairwarp.motion",
    "simulate": "hairwarp.runner",
    "Simulation": "hairwarp.runner",
    "Stepper": "hairwarp.runner",
    # many runs on Dask
    "wedge": "hairwarp.farm",
    "batch": "hairwarp.farm",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'hairwarp' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
