"""The QoS agent: per-drone session records, the arbiter that shares the priority budget, and the
client of the operator's CAMARA Quality-on-Demand API."""
