"""The pose stream: fan-out of estimates to WebSocket subscribers, and frames in over it."""
