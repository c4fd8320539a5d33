"""A flight as data: the scenario (what to fly), its faults, and what a flight recorded.

Both the harness that flies (dynqos/experiment) and the reports that read (dynqos/reports) import this;
it imports neither, so a report is written from a Recording and its Scenario without flying anything.
"""
