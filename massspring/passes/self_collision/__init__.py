"""Self-collision as a pass: the forward pass after each step (``forward.py``), its
adjoint beside it (``adjoint.py``), and the adjoint of the linearised implicit solve's
pair penalties (``penalty_adjoint.py``). Its settings are ``model.self_collision``."""
