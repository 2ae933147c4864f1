"""Robot accuracy figures from measured paths and poses: ISO 230-4 circular test, ISO 9283 poses."""
