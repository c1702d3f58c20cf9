"""Dataset adapters: each turns a recorded log into the Run the filter consumes."""
