"""Analysis built on the public Simulation API: stability predictions and ladders
(``stability``), reference solutions (``reference``), the work-precision study
(``study`` runs it, ``fits`` measures orders and cheapest runs, ``report`` prints
and writes it)."""
