"""The command lines and the folder pipelines they run (docs/layout.md)."""
