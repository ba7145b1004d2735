# One image for every service of docker-compose.yml: the daemon, the worker, the simulated
# arm (all `mirrorgonio SUBCOMMAND`) and the Dask scheduler and workers (`dask ...`, the
# same Python environment, so the workers can run the project's tasks). docs/deploy.md.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    # numba and matplotlib cache into writable places (the source is owned by root).
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    MPLCONFIGDIR=/tmp/matplotlib \
    MG_DATA_DIR=/data

WORKDIR /app

# The dependencies first, in their own layer: rebuilt only when pyproject.toml changes.
COPY pyproject.toml README.md ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

# The project itself, installed as a package: the rigs, the device profiles and the web
# page are package data (drivers/contracts/rigs, drivers/profiles, acquisition/web).
COPY acquisition ./acquisition
COPY processing ./processing
COPY drivers ./drivers
COPY sim_devices ./sim_devices
RUN pip install --no-deps . \
    && mirrorgonio --help > /dev/null

# Not root. /data is created owned by that user: a named volume mounted there for the
# first time takes this ownership, so the daemon and the worker can write to it.
RUN useradd --create-home --uid 1000 --user-group mg \
    && mkdir -p /data \
    && chown mg:mg /data
USER mg
VOLUME ["/data"]

EXPOSE 8000
ENTRYPOINT ["mirrorgonio"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
