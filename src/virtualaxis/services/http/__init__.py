"""The live drive page of ``virtualaxis serve --http`` (docs/live-page.md)."""

from virtualaxis.services.http.server import AxisPage, LivePageService, parse_host_port

__all__ = ["AxisPage", "LivePageService", "parse_host_port"]
