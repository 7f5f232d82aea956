"""The live view: dbml's allocation, budget and frames as Foxglove channels, live and recorded.

``frames`` (pure) says what is shown; ``layout`` (pure) is the shipped Foxglove layout; ``live``
follows a transport and writes to ``sink`` (foxglove-sdk, the ``viz`` extra: a WebSocket server
with the Parameters capability, and MCAP recordings).
"""

from dbml.view.live import LiveView, open_view
from dbml.view.target import ViewTarget

__all__ = ["LiveView", "ViewTarget", "open_view"]
