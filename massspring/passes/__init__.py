"""Passes: what acts on a run's state after each step of its integrator (self-collision,
the strain limit), one module or folder each."""
