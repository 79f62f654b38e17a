# mea: one image for every service of the training stack (`mea router|actor|augmenter|learner|
# evaluator|serve ...`); deploy/docker-compose.yml runs it, deploy/README.md says how.
#
#   docker build -t mea:cpu .                                   # CPU torch wheel (the default)
#   docker build -t mea:gpu --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128 .
#
# TORCH_INDEX_URL selects which build of torch==2.13.0 is installed: pip takes the wheel with the
# local version label (2.13.0+cpu, 2.13.0+cu128, ...) from that index over PyPI's plain 2.13.0.

ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/mea
# torch first, in its own layer: it is most of the image and changes least often
RUN /opt/mea/bin/pip install --extra-index-url "${TORCH_INDEX_URL}" "torch==2.13.0"
WORKDIR /src
COPY pyproject.toml README.md ./
COPY proto ./proto
COPY services ./services
COPY mea_tools ./mea_tools
RUN /opt/mea/bin/pip install --extra-index-url "${TORCH_INDEX_URL}" . \
 && /opt/mea/bin/python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"

FROM ${PYTHON_IMAGE}
ENV PATH=/opt/mea/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    OMP_NUM_THREADS=1
# the services run as an unprivileged user; /runs is the run directory's volume (a named volume
# mounted there starts out owned by this user)
RUN useradd --uid 10001 --user-group --create-home --shell /usr/sbin/nologin mea \
 && mkdir -p /runs && chown mea:mea /runs
COPY --from=build /opt/mea /opt/mea
USER mea
WORKDIR /home/mea
# every module the services import loads (torch, pybullet, opencv, zenoh), and the CLI answers
RUN python -c "import torch, pybullet, cv2, zenoh, services.plan, services.inference.main" && mea --help >/dev/null
ENTRYPOINT ["mea"]
CMD ["--help"]
