"""Data sets: the Mitsuba 3 renderer of frame bundles (`render`), the procedural scene family
(`scenes`), the relMSE table of a folder (`evaluate`) and the scenes' contact sheet."""
