"""inverse: physical-gradient (SIP) and half-inverse-gradient (HIG) training of networks through physics."""

__all__: list[str] = []
