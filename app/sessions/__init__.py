"""Localisation sessions: a filter on a map, fed frames over HTTP or WebSocket."""
