"""Offline engineering tools: analysis, tuning, table generation."""
