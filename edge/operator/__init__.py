"""The operator's network APIs as the edge calls them: one client (client.py: one HTTP session, tokens,
retries, correlators, errors by kind) and a thin module per API (qod.py, profiles.py, booking.py,
connectivity.py). The QoS agent and the fleet planner each open one OperatorClient and put every API
they use on it."""
