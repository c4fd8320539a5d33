"""Watching a flight from outside: the Foxglove view and the MCAP recorder (one observer), the
conversion of dynqos messages into Foxglove's schemas, and the Foxglove layout."""
