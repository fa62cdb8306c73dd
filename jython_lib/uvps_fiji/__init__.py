"""uvps_fiji: the Fiji/ImageJ 1.x side of uvps (Jython 2.7).

``bridge_logic`` is pure Python (also imported by CPython tests); ``runner``, ``display`` and
``dialogs`` use ImageJ classes and run only inside ImageJ/Fiji. Nothing is imported here so that
CPython can import ``uvps_fiji.bridge_logic`` without ImageJ.
"""
