# Image that runs `commission`; SocketCAN needs --network host (and the can0 link up on the host).
FROM python:3.11-slim
WORKDIR /opt/drive-commission
COPY pyproject.toml README.md ./
COPY src ./src
COPY sim_drive ./sim_drive
COPY configs ./configs
COPY drivers ./drivers
ENV COMMISSION_DRIVERS=/opt/drive-commission/drivers
RUN pip install --no-cache-dir . && useradd --create-home commission
USER commission
WORKDIR /home/commission
ENTRYPOINT ["commission"]
CMD ["--help"]
