"""Shared plumbing of library and tasks: atomic files, thread counts, settings checks, tables and figures."""
