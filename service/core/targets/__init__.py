"""The target field, the ring codes, and finding, reading and identifying targets in an image."""
