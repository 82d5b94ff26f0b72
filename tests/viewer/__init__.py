"""viewer/: the live and saved-run viewer in a real browser."""
