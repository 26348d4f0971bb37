"""File formats at the edge of hp-edge: history CSVs (``history``)."""
