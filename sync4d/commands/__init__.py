"""Implementations of the ``python -m sync4d`` commands (each module has ``main(args)``)."""
