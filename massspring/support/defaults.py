"""Defaults and limits shared by the API, the scenes and the CLI, written once."""

VERSION = "0.2.0"  # the package's version, as in pyproject.toml (``massspring.__version__``)
GRAVITY = (0.0, 0.0, -9.81)  # m/s^2, the default gravity of models, meshes, generators and scene files
PRECISIONS = ("f64", "f32")  # the run precisions, the default first
MAX_STEPS = 2**62  # steps a run, a restart or a step() call may count (int64 with room)
FALLBACK_DT = 1e-2  # s, an explicit integrator's suggested dt where no stiffness limits it
