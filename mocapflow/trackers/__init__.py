"""Live trackers: what the vendor adapters share (frame numbering, clock mapping, a push-driven source node) and the
stand-in servers that speak each vendor's protocol from a marker file."""
