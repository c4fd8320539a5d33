"""The drone's half of the loop: flight-controller link, camera, monitors, supervisor, fallback PID."""
