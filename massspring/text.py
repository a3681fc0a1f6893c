"""How values are written for people: the CLI's output and the error messages."""


def format_seconds(dt):
    """A time step for people: '1/60 s' when 1/dt is a whole number (to 1e-6), else '2e-05 s'."""
    inverse = 1.0 / dt
    if inverse >= 2 and abs(inverse - round(inverse)) <= 1e-6 * inverse:
        return f"1/{round(inverse)} s"
    return f"{dt:.4g} s"
