"""Scale-out on Ray Serve: stateless ingress replicas in front of session owners (one per shard of
sessions), over a data directory every node mounts. Ray is imported only by `server.cluster.serve`,
so the single-process service never needs it (``pip install '.[cluster]'`` adds it)."""
