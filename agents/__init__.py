"""The robot brain: controllers, behaviours, state machine and the agent runtime."""
