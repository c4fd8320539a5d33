"""The circle detector: the vision (pure), the assembler of a frame's chunks, and the service."""
