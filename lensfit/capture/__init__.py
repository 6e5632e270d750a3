"""Planning a capture before shooting: the shot plan (``plan``), its printed list (``shotlist``)
and printable targets (``printable``)."""
