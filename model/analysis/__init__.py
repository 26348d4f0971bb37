"""The DataFrame layer of the analysis: measured-side figures, learned compressors, calibration
windows, optimization and forecasts in canonical columns (ARCHITECTURE.md)."""
