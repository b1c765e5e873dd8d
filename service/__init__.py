"""Recal's service layer: the ``recal`` command line, file formats, sessions, store and API."""
