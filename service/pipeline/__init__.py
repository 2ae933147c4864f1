"""From a frame to a measured pose: detection, decoding, identification, resection, ROI tracking."""
