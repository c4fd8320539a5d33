"""The experiment: scenarios and profiles, the runner that starts every process of a flight (one drone
or a fleet), the faults it injects, what it records, the demo and the studies beyond it."""
