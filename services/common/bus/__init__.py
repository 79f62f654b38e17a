"""Message bus: one interface (base.Bus), an in-process and a Zenoh implementation."""

from services.common.bus.base import AliveWatch, Bus, Delivery, Subscription
from services.common.bus.inproc import Hub, InProcBus

__all__ = ["AliveWatch", "Bus", "Delivery", "Hub", "InProcBus", "Subscription"]
