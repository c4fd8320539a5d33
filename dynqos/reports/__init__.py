"""What a run folder holds: each flight's summary.json, time series and plots, the fleet's summary,
aggregates over repeated runs, and report.md."""
