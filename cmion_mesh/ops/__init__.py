"""What an operator runs a daemon with: logs, a settings file, and (beside them) service and metrics."""
