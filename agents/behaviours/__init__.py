"""Behaviour layers: navigation and formation."""
