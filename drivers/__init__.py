"""Robot drivers: a small protocol and backends chosen by name (sim, arcos, canopen)."""
