"""Output (and input) files: atomic writes (``files``), states (``state``), pictures
(``camera``, ``render``)."""
