"""Single-file training algorithms: A2C (on-policy) and SAC (off-policy), each with a typed Args."""
