"""Output (and input) files: atomic writes (``files``), states (``state``), OBJ meshes
(``obj``), per-frame export (``frames``), pictures (``camera``, ``render``)."""
