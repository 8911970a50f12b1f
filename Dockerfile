# Fringescope: the live service on the built-in simulator (or real devices via FRINGESCOPE_*).
#
#   docker build -t fringescope .
#   docker run -p 8000:8000 -e FRINGESCOPE_API_TOKEN=secret -v fringescope-data:/data fringescope
#   → http://HOST:8000/  (state-changing routes and /viser/ need the token)
#
# Inside the container the server listens on 0.0.0.0, so it refuses to start
# without FRINGESCOPE_API_TOKEN unless FRINGESCOPE_INSECURE=1 is given (trusted
# networks only). Every setting of app/config.py is an environment variable
# FRINGESCOPE_<NAME>, e.g. FRINGESCOPE_CAMERA=opencv FRINGESCOPE_CAMERA_SOURCE=0.
# Calibrations and recordings live in the volume /data.
#
# The same image is a Dask worker for `fringescope reprocess --scheduler tcp://HOST:8786`
# (README "Reprocessing recordings on a cluster"); recordings and outputs on shared storage
# mounted at the same path on every machine:
#   docker run --network host -v /shared:/shared -e NUMBA_NUM_THREADS=1 fringescope
#       dask worker tcp://HOST:8786 --nworkers auto --nthreads 1
# and `dask scheduler --port 8786 --no-dashboard` for the scheduler.
FROM python:3.11-slim

# PATH spelled out: the official image sets the same, an imported stand-in sets none.
ENV PATH=/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    NUMBA_THREADING_LAYER=workqueue \
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    FRINGESCOPE_HOST=0.0.0.0 \
    FRINGESCOPE_PORT=8000 \
    FRINGESCOPE_DATA_DIR=/data

# Metadata first, while the image is small (cheap layers on copy-based storage).
RUN useradd --system --create-home --uid 10001 --home-dir /home/fringescope fringescope \
    && mkdir -p /data /tmp/numba-cache \
    && chown fringescope:fringescope /data /tmp/numba-cache
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('FRINGESCOPE_PORT', '8000'), timeout=4)"]
CMD ["fringescope", "serve"]

# Dependencies change less often than the code: their own layer, reused on rebuilds.
COPY pyproject.toml README.md /tmp/src/
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('/tmp/src/pyproject.toml', 'rb'))['project']['dependencies']))" > /tmp/requirements.txt \
    && pip install --no-cache-dir -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt
COPY app /tmp/src/app
COPY static /tmp/src/static
# app.main serves the dashboard from static/ beside the installed package.
RUN pip install --no-cache-dir --no-deps /tmp/src \
    && site="$(cd / && python -c 'import app, pathlib; print(pathlib.Path(app.__file__).resolve().parent.parent)')" \
    && cp -r /tmp/src/static "$site/static" \
    && rm -rf /tmp/src

WORKDIR /home/fringescope
USER fringescope
