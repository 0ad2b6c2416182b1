"""``report.html``: what a conversion made, on one self-contained page (``report.page``)."""
