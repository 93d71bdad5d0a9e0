"""File formats, one module per format or role. The domain types (``Groom``, ``Collider``, ``Model``) import none
of these at module level; ``pxr`` is imported inside the functions that need it.

- :mod:`hairwarp.io.usd_common`: what every USD reader and writer shares (layout, units, ``Vt`` copies).
- :mod:`hairwarp.io.cache`: the animation cache writer: one layer per frame, assembled with value clips.
- :mod:`hairwarp.io.background`: the same writer in a second process.
- :mod:`hairwarp.io.usd_groom`: static grooms written to and read from USD.
- :mod:`hairwarp.io.usd_anim`: colliders that follow a Mesh prim's animation in a USD stage.
- :mod:`hairwarp.io.usd_inspect`: caches read back frame by frame, and their summary.
- :mod:`hairwarp.io.tfx`: AMD TressFX hair (``.tfx``) and collision meshes (``.tfxmesh``).
- :mod:`hairwarp.io.cem_hair`: Cem Yuksel's ``.hair`` files, read and written.
"""
