"""The mission planner: missions as references (pure) and the service that publishes them."""
