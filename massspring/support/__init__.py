"""Small shared pieces every layer may use: defaults, errors, argument validation, text,
progress lines, optional extras, and host memory checks."""
