"""The surgery task's learning configs (``agents``)."""
