"""Analysis and release command lines, each run as ``python -m shield_nav.tools.<name>`` (docs/architecture.md)."""
