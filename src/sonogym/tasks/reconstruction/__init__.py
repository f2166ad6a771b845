"""The reconstruction task's learning configs (``agents``)."""
