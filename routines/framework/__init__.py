"""What every routine stands on: the plan and result types, the guard, records, gates, the registry and the runner."""
