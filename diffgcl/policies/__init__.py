"""Global policies on observations (MDGPS)."""
