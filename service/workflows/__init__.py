"""The offline verbs' work: calibrations, simulation, the targets sheet, the demo."""
