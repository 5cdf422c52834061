"""Depth heads, one per file, behind the one interface of :mod:`deltar.models.heads.base`.

:data:`deltar.models.network.HEADS` names them for :class:`~deltar.models.network.DeltarNet`.
"""
