# Image that runs `commission`; SocketCAN needs --network host (and the can0 link up on the host).
FROM python:3.11-slim
WORKDIR /tmp/drive-commission
COPY pyproject.toml README.md ./
COPY src ./src
COPY sim_drive ./sim_drive
COPY configs ./configs
COPY drivers ./drivers
# the same install as a user's: the wheel, with drivers/ and configs/ inside it; the sources go
RUN pip install --no-cache-dir . && rm -rf /tmp/drive-commission && useradd --create-home commission
USER commission
WORKDIR /home/commission
# numba's kernels compiled once, into the user's cache (site-packages belongs to root)
RUN commission --warm-cache
ENTRYPOINT ["commission"]
CMD ["--help"]
