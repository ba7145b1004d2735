# One image for every service of docker-compose.yml: the daemon, the worker, the simulated
# arm (all `mirrorgonio SUBCOMMAND`) and the Dask scheduler and workers (`dask ...`, the
# same Python environment, so the workers can run the project's tasks). docs/deploy.md.
# Debian 12 named, so that a rebuild gets the same system libraries' versions.
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    # numba and matplotlib cache into writable places (the source is owned by root).
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    MPLCONFIGDIR=/tmp/matplotlib \
    MG_DATA_DIR=/data

WORKDIR /app

# libgphoto2 and its command-line tool: `docker compose exec daemon gphoto2 --auto-detect` says
# which cameras the container sees (the gphoto2 Python package carries its own libgphoto2).
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgphoto2-6 gphoto2 \
    && rm -rf /var/lib/apt/lists/*

# The dependencies first, in their own layer (rebuilt only when pyproject.toml or the
# constraints change): those of pyproject.toml and of its gphoto2 extra (the real camera),
# at the versions constraints.txt pins, every one (`make constraints` writes it): two builds
# of one commit install the same packages.
COPY pyproject.toml README.md constraints.txt ./
RUN python -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; print('\n'.join(p['dependencies'] + p['optional-dependencies']['gphoto2']))" \
        > /tmp/requirements.txt \
    && pip install -c constraints.txt -r /tmp/requirements.txt setuptools wheel \
    && rm /tmp/requirements.txt

# The project itself, installed as a package: the rigs, the device profiles and the web
# page are package data (drivers/contracts/rigs, drivers/profiles, acquisition/daemon/web).
COPY acquisition ./acquisition
COPY processing ./processing
COPY drivers ./drivers
COPY sim_devices ./sim_devices
RUN pip install --no-deps --no-build-isolation . \
    && mirrorgonio --help > /dev/null \
    && python -c "import gphoto2"

# Not root. /data is created owned by that user: a named volume mounted there for the
# first time takes this ownership, so the daemon and the worker can write to it. The user
# is in plugdev (cameras, by libgphoto2's udev rules) and dialout (serial ports), the groups
# that own those device nodes on a Debian or Ubuntu host (docker-compose.rig.yml).
RUN useradd --create-home --uid 1000 --user-group --groups plugdev,dialout mg \
    && mkdir -p /data \
    && chown mg:mg /data
USER mg
VOLUME ["/data"]

EXPOSE 8000
ENTRYPOINT ["mirrorgonio"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
