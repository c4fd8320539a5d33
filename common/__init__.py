"""What the onboard and edge halves share: messages, keys, config, transport, clocks, statistics."""
