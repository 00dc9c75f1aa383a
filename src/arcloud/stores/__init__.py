"""Object store adapters: ``memory`` (embedded, the default) and ``redis`` (many workers, many machines)."""
