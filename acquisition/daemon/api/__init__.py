"""The daemon's REST API: one router per resource."""
