"""The QoS agent: per-drone session records, the arbiter that shares the priority budget, and the calls
that keep each drone's grant with the operator (over edge/operator/)."""
