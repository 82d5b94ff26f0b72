"""The documentation and the package's structure: docs' commands and links, the layering of docs/architecture.md."""
