"""The robot model's identification from measured flange poses."""
