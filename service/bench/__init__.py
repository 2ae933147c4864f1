"""``posecell bench``: accuracy, speed with its condition matrix, faults."""
