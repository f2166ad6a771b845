"""The navigation task's learning configs (``agents``)."""
