"""One module per ``recal`` verb: ``add_parser(parser)`` and ``run(args) -> int``."""
