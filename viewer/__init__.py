"""The browser viewer: static HTML, JavaScript and CSS that the service serves at ``/``.

Package data only (no Python beyond this file): installed as ``cfsr_live.viewer`` so that
:func:`cfsr_live.service.app.viewer_dir` finds it in a wheel as in the checkout.
"""
