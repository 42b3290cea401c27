"""What every routine stands on: the plan and result types, the run's context, the guard, records, gates, the registry and the runner."""
