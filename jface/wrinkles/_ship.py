"""Writes the fit layouts that jface ships (:data:`jface.wrinkles._fit.SHIPPED_LAYOUTS`):
``python -m jface.wrinkles._ship``, after a change that their test finds."""

from jface.wrinkles._fit import ship_layouts

if __name__ == "__main__":
    ship_layouts()
