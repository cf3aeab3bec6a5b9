"""Subcommands of ``colmap-miho``; one module per command (see ``colmap_miho.cli``)."""
