"""The gesture database: its schema, build, reading, atomic storage and edits.

=================  ==========================================================
``schema``         every dataset, dtype, shape, unit and ``SCHEMA_VERSION``
``storage``        temp file + rename + lock for every write; ``edit`` for changes
``store``          the operations writers ask of an open file (create, append, attrs, delete)
``arrayfile``      arrays cached beside a database (the refiner's training data)
``cluster``        every use of Dask: ``scheduler`` = ``"local:N"``, ``"tcp://..."`` or a client
``build``          recordings -> features -> HDF5
``database``       :class:`Database`, what :func:`gesturedb.open` returns
``edit``           saved masks and control features of an existing file
``keywords``       keyword sub-databases (stored in the file)
``export``         a keyword sub-database as a database file of its own
``shardfiles``     ``gesturedb shard``: shard files of whole recordings + an index file
``shards``         rank-sum search over shards resident on Dask workers (placed through ``cluster``)
=================  ==========================================================
"""
