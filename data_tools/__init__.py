"""Command-line tools that build focal-stack datasets (synthetic, Mitsuba, RAW).

They import the library; the library never imports them.
"""
