"""``pcc``: the command-line doorway. :mod:`pcc_ros.cli.main` parses and dispatches; each
command is one small module here (or a library module the table in ``main`` names) exposing
``add_arguments(parser)`` and ``run(args) -> int``.

Nothing in the package imports this folder; this ``__init__`` imports nothing.
"""
