"""The analysis layer over the cycle model: fouling forecast, cost of fouling, CIP timing (SPEC §10)."""
