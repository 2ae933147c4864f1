"""A camera's pose from one image (resection), from several (intersection), over time."""
