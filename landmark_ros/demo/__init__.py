"""The process launcher and the simulated team demo (make demo)."""
