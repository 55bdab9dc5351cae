"""The edge: the runner that schedules the stages on an executor, and the command line."""
