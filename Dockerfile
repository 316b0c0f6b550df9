# forcecal on Debian 12: the container installs through the same `make setup`
# the README's commands use, so it cannot drift from what CI tests.
FROM debian:12
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends make ca-certificates \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /forcecal
COPY . .
RUN make setup && rm -rf /var/lib/apt/lists/*
CMD ["make", "test"]
