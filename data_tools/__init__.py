"""Tools that build benchmark inputs from the shared real data (never part of the installed package)."""
