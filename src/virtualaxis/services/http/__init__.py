"""The live drive page of ``virtualaxis serve --http`` (docs/live-page.md)."""

from virtualaxis.services.http.server import parse_host_port
from virtualaxis.services.http.service import AxisPage, LivePageService

__all__ = ["AxisPage", "LivePageService", "parse_host_port"]
