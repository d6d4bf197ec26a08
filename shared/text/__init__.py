"""Text encoders that embed prompts and queries (used by the simulated VL backend and by
evaluation)."""
