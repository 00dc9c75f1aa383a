"""Generated code of ``proto/arcloud/v1`` (``make proto``); do not edit."""
