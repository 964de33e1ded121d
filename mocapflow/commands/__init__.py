"""Subcommands of the mocapflow CLI: each module defines ``register(subparsers)``."""
