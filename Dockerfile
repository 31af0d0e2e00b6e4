# One image for every service of compose.yaml: `twin router`, `twin conductor`, `twin agent KIND`,
# `twin robot play`. Build: docker build -t twin:latest .
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app

# dependencies first (cached while only the sources change); pybullet and rerun ship manylinux wheels
COPY pyproject.toml README.md ./
RUN mkdir -p protocol agents conductor recordings bench \
 && touch protocol/__init__.py agents/__init__.py conductor/__init__.py recordings/__init__.py bench/__init__.py \
 && pip install . && pip uninstall -y twin

COPY protocol ./protocol
COPY agents ./agents
COPY conductor ./conductor
COPY scenes ./scenes
COPY recordings ./recordings
COPY bench ./bench
RUN pip install --no-deps . && mkdir -p /runs

# Zenoh's default port; every twin program reads TWIN_CONNECT / TWIN_LISTEN / TWIN_ENSEMBLE / TWIN_TLS_*
EXPOSE 7447
CMD ["twin", "--help"]
