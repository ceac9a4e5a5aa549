"""The report stage: per-session figures and the campaign page (matplotlib, pandas)."""
