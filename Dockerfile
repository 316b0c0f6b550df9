# forcecal on Debian 12: the container installs through the same `make setup`
# the README's commands use, so it cannot drift from what CI tests.
#   docker build --build-arg GIT_COMMIT=$(git rev-parse HEAD) -t forcecal .
#   docker run --rm forcecal                                   # make test, as user 1000
#   docker run --rm --user "$(id -u):$(id -g)" --shm-size=1g -v "$PWD/runs:/forcecal/runs" forcecal make demo
# The image runs as the unprivileged user `forcecal` (uid 1000) by default; any other uid
# works too (`--user 12345`, as clusters do): the caches and runs/ are writable by everyone (and a
# uid that cannot write to a folder another uid made inside a cache gets its own: forcecal/caches.py).
FROM debian:12
# the commit the image is built from (no .git in the image): recorded in every result's
# versions.git_commit (forcecal.provenance.git_commit)
ARG GIT_COMMIT=""
ENV FORCECAL_GIT_COMMIT=${GIT_COMMIT}
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends make ca-certificates \
    && apt-get clean && rm -rf /var/lib/apt/lists/*
# containers usually forbid the cross-memory attach OpenMPI's shared-memory transport tries first
ENV OMPI_MCA_btl_vader_single_copy_mechanism=none
# the numba and FFCx caches (the Makefile's defaults, also for commands run without make), and a
# HOME any uid can write (tools such as matplotlib and OpenMPI write there)
ENV XDG_CACHE_HOME=/forcecal/.cache NUMBA_CACHE_DIR=/forcecal/.cache/numba HOME=/forcecal/.cache/home \
    MPLCONFIGDIR=/forcecal/.cache/matplotlib
WORKDIR /forcecal
COPY . .
# make setup installs the Debian packages; their downloaded .deb files and lists are removed in
# the same layer. The caches, runs/ and the tree itself (pytest's cache) are writable by any
# uid; OpenMPI then needs no root override (the Makefile's OMPI_ALLOW_RUN_AS_ROOT is harmless).
RUN make setup \
    && apt-get clean && rm -rf /var/lib/apt/lists/* /var/cache/apt/archives/*.deb \
    && useradd --uid 1000 --no-create-home --home-dir /forcecal/.cache/home forcecal \
    && mkdir -p /forcecal/.cache/numba /forcecal/.cache/home /forcecal/.cache/matplotlib /forcecal/runs \
    && chmod -R a+rwX /forcecal/.cache /forcecal/runs \
    && chmod a+rwX /forcecal
USER 1000
CMD ["make", "test"]
