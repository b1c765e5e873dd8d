"""The REST API (contracts §9)."""
