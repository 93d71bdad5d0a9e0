"""Device side of hairwarp: ``@wp.kernel`` and ``@wp.func`` only, no host logic.

Installed as ``hairwarp.kernels`` (see ``pyproject.toml``). Importing this folder as a
top-level ``kernels`` package would load a second copy of every module, and Warp would
compile each kernel twice, so that import is refused.
"""

if __name__ != "hairwarp.kernels":
    raise ImportError(
        f"the kernels folder was imported as {__name__!r}; import it as 'hairwarp.kernels' "
        "(install the project with `pip install -e .`)"
    )
