"""mocapflow: optical motion capture to labelled, gap-free markers and a live skeleton."""

__version__ = "0.1.0"
