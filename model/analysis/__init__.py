"""The DataFrame layer of the analysis: measured-side figures, learned compressors, calibration
windows, optimization, fouling forecasts and CIP timing in canonical columns (ARCHITECTURE.md)."""
