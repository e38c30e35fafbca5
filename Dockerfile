# The wallcull server, simulated render nodes and the load driver, in one image.
#   docker build -t wallcull .
#   docker run --rm -p 8000:8000 -e WALLCULL_TOKEN=secret wallcull        # the server
# docker-compose.yml runs a whole wall (server + nodes + driver) from this image.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    WALLCULL_STATE=/var/lib/wallcull

WORKDIR /app

# Dependencies first (a layer that survives source edits): install the project's requirements
# from pyproject.toml alone, then the sources.
COPY pyproject.toml README.md ./
COPY clients/pyproject.toml ./clients/
RUN python -c "import tomllib; d = tomllib.load(open('pyproject.toml', 'rb')); \
c = tomllib.load(open('clients/pyproject.toml', 'rb')); \
print('\n'.join(d['project']['dependencies'] + d['project']['optional-dependencies']['nats'] \
+ [r for r in c['project']['dependencies'] if r != 'wallcull']))" > /tmp/requirements.txt \
 && pip install -r /tmp/requirements.txt

COPY LICENSE ./
COPY wallcull ./wallcull
COPY clients ./clients
COPY examples ./examples
COPY scenes ./scenes
RUN pip install --no-deps . ./clients \
 && useradd --create-home --uid 10001 wallcull \
 && mkdir -p /tmp/numba-cache /var/lib/wallcull \
 && chown wallcull /tmp/numba-cache /var/lib/wallcull
USER wallcull
# Compile every numba kernel now, as the user that runs the server, into NUMBA_CACHE_DIR: a
# fresh container loads them in milliseconds and answers its health check in seconds instead
# of compiling for a minute or more at its first start (wallcull.warm).
RUN python -m wallcull.warm
# walls (SQLite), credentials' digests, frame numbers and uploads: kept across restarts
VOLUME ["/var/lib/wallcull"]

EXPOSE 8000
HEALTHCHECK --interval=5s --timeout=4s --start-period=10s --retries=20 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/health', timeout=3)"]
# The token comes from the environment: WALLCULL_TOKEN (read by `wallcull serve`); so do
# WALLCULL_STATE, WALLCULL_CORS_ORIGINS and WALLCULL_LIMITS.
CMD ["wallcull", "serve", "--host", "0.0.0.0", "--port", "8000"]
