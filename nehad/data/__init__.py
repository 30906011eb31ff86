"""Dataset readers and the synthetic scene generator (numpy only, no torch)."""
