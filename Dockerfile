# forcecal on Debian 12: the container installs through the same `make setup`
# the README's commands use, so it cannot drift from what CI tests.
#   docker build -t forcecal .
#   docker run --rm forcecal                                   # make test
#   docker run --rm --shm-size=1g -v "$PWD/runs:/forcecal/runs" forcecal make demo
FROM debian:12
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends make ca-certificates \
    && rm -rf /var/lib/apt/lists/*
# containers usually forbid the cross-memory attach OpenMPI's shared-memory transport tries first
ENV OMPI_MCA_btl_vader_single_copy_mechanism=none
WORKDIR /forcecal
COPY . .
RUN make setup && rm -rf /var/lib/apt/lists/*
CMD ["make", "test"]
