"""Subcommands of the fleetmap CLI: each module has ``register(subparsers)`` setting ``func``."""
