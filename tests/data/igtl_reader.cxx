// An OpenIGTLink reader built on Debian's libopenigtlink (tests/test_igtl.py compiles it when the library is
// installed): connects to HOST PORT, reads COUNT messages, checks each body's CRC with the library's Unpack(1)
// and prints one line per message as JSON: type, device, crc_ok and, for TRANSFORM, the 4x4 matrix; for
// POLYDATA, the points, the lines (cells) and the number of vertices and polygons.
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <list>

#include "igtlClientSocket.h"
#include "igtlMessageHeader.h"
#include "igtlPolyDataMessage.h"

#include <vector>
#include "igtlTransformMessage.h"

static void cells(const char* name, igtl::PolyDataCellArray* array) {
  std::printf(", \"%s\": [", name);
  unsigned int n = array ? array->GetNumberOfCells() : 0;
  for (unsigned int i = 0; i < n; i++) {
    std::list<igtlUint32> cell;
    array->GetCell(i, cell);
    std::printf("%s[", i ? ", " : "");
    bool first = true;
    for (std::list<igtlUint32>::iterator it = cell.begin(); it != cell.end(); ++it) {
      std::printf("%s%u", first ? "" : ", ", *it);
      first = false;
    }
    std::printf("]");
  }
  std::printf("]");
}

int main(int argc, char* argv[]) {
  if (argc != 4) {
    std::fprintf(stderr, "usage: igtl_reader HOST PORT COUNT\n");
    return 2;
  }
  igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
  if (socket->ConnectToServer(argv[1], std::atoi(argv[2])) != 0) {
    std::fprintf(stderr, "cannot connect\n");
    return 1;
  }
  int count = std::atoi(argv[3]);
  for (int k = 0; k < count; k++) {
    igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
    header->InitPack();
    if (socket->Receive(header->GetPackPointer(), header->GetPackSize()) != header->GetPackSize()) return 1;
    header->Unpack();
    const char* type = header->GetDeviceType();
    std::printf("{\"type\": \"%s\", \"device\": \"%s\"", type, header->GetDeviceName());
    if (std::strcmp(type, "TRANSFORM") == 0) {
      igtl::TransformMessage::Pointer msg = igtl::TransformMessage::New();
      msg->SetMessageHeader(header);
      msg->AllocatePack();
      socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize());
      int c = msg->Unpack(1);
      igtl::Matrix4x4 m;
      msg->GetMatrix(m);
      std::printf(", \"crc_ok\": %s, \"matrix\": [", (c & igtl::MessageHeader::UNPACK_BODY) ? "true" : "false");
      for (int i = 0; i < 4; i++)
        std::printf("%s[%.9g, %.9g, %.9g, %.9g]", i ? ", " : "", m[i][0], m[i][1], m[i][2], m[i][3]);
      std::printf("]");
    } else if (std::strcmp(type, "POLYDATA") == 0) {
      igtl::PolyDataMessage::Pointer msg = igtl::PolyDataMessage::New();
      msg->SetMessageHeader(header);
      msg->AllocatePack();
      socket->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize());
      int c = msg->Unpack(1);
      std::printf(", \"crc_ok\": %s, \"points\": [", (c & igtl::MessageHeader::UNPACK_BODY) ? "true" : "false");
      igtl::PolyDataPointArray* points = msg->GetPoints();
      int n = points ? points->GetNumberOfPoints() : 0;
      for (int i = 0; i < n; i++) {
        igtlFloat32 p[3];
        points->GetPoint(i, p);
        std::printf("%s[%.9g, %.9g, %.9g]", i ? ", " : "", p[0], p[1], p[2]);
      }
      std::printf("]");
      cells("lines", msg->GetLines());
      cells("vertices", msg->GetVertices());
      cells("polygons", msg->GetPolygons());
      std::printf(", \"attributes\": {");
      for (int a = 0; a < msg->GetNumberOfAttributes(); a++) {
        igtl::PolyDataAttribute* att = msg->GetAttribute(a);
        std::vector<igtlFloat32> v(att->GetSize() * att->GetNumberOfComponents());
        if (!v.empty()) att->GetData(&v[0]);
        std::printf("%s\"%s\": {\"type\": %d, \"values\": [", a ? ", " : "", att->GetName(), (int)att->GetType());
        for (size_t i = 0; i < v.size(); i++) std::printf("%s%.9g", i ? ", " : "", v[i]);
        std::printf("]}");
      }
      std::printf("}");
    } else {
      socket->Skip(header->GetBodySizeToRead(), 0);
    }
    std::printf("}\n");
    std::fflush(stdout);
  }
  socket->CloseSocket();
  return 0;
}
