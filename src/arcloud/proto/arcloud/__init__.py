"""Generated protobuf packages (``make proto``); mirrors ``proto/arcloud``."""
