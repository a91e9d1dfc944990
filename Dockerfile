# syntax=docker/dockerfile:1
# MFGNet registration service: torch-free runtime (numpy + ONNX Runtime + FastAPI), one uvicorn
# process per container; scale with replicas, not workers. Build and run: docs/DEPLOYMENT.md.
#
#   docker build -t mfgnet .
#   docker run --rm -p 8080:8080 mfgnet
#
# Base image: Python 3.11.7 (the version the project is developed and tested on), Debian bookworm
# slim, pinned by tag AND by digest (the multi-arch index digest published for this tag). Override
# with --build-arg PYTHON_IMAGE=... (a mirror, or a newer patch release) when needed.
ARG PYTHON_IMAGE=python:3.11.7-slim-bookworm@sha256:8f64a67710f3d981cf3008d6f9f1dbe61accd7927f165f4e37ea3f8b883ccc3f

# ---------------------------------------------------------------------------------------------
# build: the project wheel (with the bundled ONNX models as package data) + wheels of the
# `serve` extra's dependencies. Anything that ever needs compiling happens here, never below.
FROM ${PYTHON_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
# .dockerignore is an allow-list: pyproject + the service/model/export packages, no benchmarks
# (bench/), results, data, checkpoints, runs, tests, docs, caches or virtual environments.
COPY . .
RUN pip wheel --no-deps --wheel-dir /wheels . \
 && printf '%s[serve]\n' /wheels/mfgnet-*.whl > /wheels/requirements-serve.txt \
 && pip wheel --wheel-dir /wheels --requirement /wheels/requirements-serve.txt \
 && python -c "import sys, zipfile, glob; names = zipfile.ZipFile(glob.glob('/wheels/mfgnet-*.whl')[0]).namelist(); onnx = [n for n in names if n.startswith('service/models/') and n.endswith('.onnx')]; print('bundled ONNX graphs:', onnx); sys.exit(0 if onnx else 'no ONNX model in the wheel')"

# ---------------------------------------------------------------------------------------------
# runtime: the wheel with only the `serve` extra (no torch, no compilers), installed offline from
# the build stage's wheels through a bind mount, so no wheel file stays in a layer.
FROM ${PYTHON_IMAGE} AS runtime

LABEL org.opencontainers.image.title="mfgnet" \
      org.opencontainers.image.description="MFGNet point-cloud registration service (ONNX Runtime, Open Inference Protocol v2 health routes)" \
      org.opencontainers.image.licenses="MIT"

RUN --mount=type=bind,from=build,source=/wheels,target=/wheels \
    pip install --no-cache-dir --disable-pip-version-check --no-index --find-links=/wheels \
        --requirement /wheels/requirements-serve.txt \
 && groupadd --system --gid 10001 mfgnet \
 && useradd --system --uid 10001 --gid 10001 --no-create-home --home-dir /nonexistent \
        --shell /usr/sbin/nologin mfgnet

# Settings: every MFGNET_* variable (service/core/config.py); these are the container defaults.
# OMP_NUM_THREADS=1 keeps OpenMP/BLAS from spawning a thread per core on top of ONNX Runtime's own
# MFGNET_THREADS intra-op threads. ORT_DISABLE_TELEMETRY=1: ONNX Runtime sends no telemetry and writes no
# device id under $HOME (the service sets it too). Bytecode was compiled at install time; the root filesystem may
# be read-only at run time, so nothing is written next to the code.
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    OMP_NUM_THREADS=1 \
    ORT_DISABLE_TELEMETRY=1 \
    MFGNET_HOST=0.0.0.0 \
    MFGNET_PORT=8080 \
    MFGNET_THREADS=2

WORKDIR /tmp
USER 10001:10001
EXPOSE 8080

# Ready = every model loaded and warmed up (OIP v2). Standard library only: the image has no curl.
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; url = 'http://127.0.0.1:%s/v2/health/ready' % os.environ.get('MFGNET_PORT', '8080'); sys.exit(0 if urllib.request.urlopen(url, timeout=4).status == 200 else 1)"]

# One uvicorn process; host, port, threads and limits come from the MFGNET_* environment.
CMD ["mfgnet", "serve"]
