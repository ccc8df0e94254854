"""Subcommands of the ``schlieren`` CLI: one module each, discovered by ``workers.cli``."""
