"""A run: ``Simulation`` (``simulation.py``) steps a Model with one integrator and a list
of passes on the device bundle; the control schedule (``schedule.py``); the operators
of Eq. 15 for analysis (``operators.py``)."""
