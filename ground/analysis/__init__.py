"""Analysis: replay of frame sets, solve reports, results logs and plots."""
