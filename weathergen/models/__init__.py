"""Optical-flow networks behind one contract, looked up by name."""
