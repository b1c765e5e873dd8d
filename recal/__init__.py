"""``python -m recal``: the same command line as ``recal`` (contracts §6). The CLI itself is
``service.cli``; this package holds only the entry point, so that the module's name is the
command's."""
