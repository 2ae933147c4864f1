"""What is kept: measurements (SQLite), calibrations (versioned files), the file formats."""
