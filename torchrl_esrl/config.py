"""Configuration errors and checks run before any expensive work starts."""
from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is invalid; the message is one line naming the field and what is allowed."""
