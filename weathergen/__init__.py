"""weathergen: physically placed weather for optical-flow data, and weather attacks on flow networks."""

__version__ = "0.1.0"
