"""Service infrastructure: settings, map registry, scan cache, metrics, errors."""

from service.core.logs import quiet_noisy_loggers

# before anything here imports faiss (the registry does): its loader logs failed probes at INFO
quiet_noisy_loggers()
