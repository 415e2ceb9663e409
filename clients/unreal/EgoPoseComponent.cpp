// See EgoPoseComponent.h: Unreal glue, documentation only (not compiled by the project's tests).
#include "EgoPoseComponent.h"

#include "DrawDebugHelpers.h"
#include "EgoPoseProtocol.h"
#include "HeadMountedDisplayFunctionLibrary.h"
#include "IWebSocket.h"
#include "WebSocketsModule.h"

namespace {
constexpr int32 kParents[22] = {-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19};

egopose::Vec3 ToVec(const FVector& V) { return {V.X, V.Y, V.Z}; }
egopose::Quat ToQuat(const FQuat& Q) { return {Q.X, Q.Y, Q.Z, Q.W}; }

// One controller in the protocol's frame; untracked (valid false) unless position and orientation are tracked.
egopose::Pose7 Controller(UObject* World, EControllerHand Hand, bool& bValid) {
    FXRMotionControllerData Data;
    UHeadMountedDisplayFunctionLibrary::GetMotionControllerData(World, Hand, Data);
    bValid = Data.bValid && Data.TrackingStatus == ETrackingStatus::Tracked;
    if (!bValid) return {0, 0, 0, 0, 0, 0, 1};
    // Grip poses come in world space: back into the tracking space the protocol's stage frame is.
    const FTransform WorldToTracking = UHeadMountedDisplayFunctionLibrary::GetTrackingToWorldTransform(World).Inverse();
    const FVector P = WorldToTracking.TransformPosition(Data.GripPosition);
    const FQuat Q = WorldToTracking.TransformRotation(Data.GripRotation);
    return egopose::controller_from_grip(egopose::from_unreal_position(ToVec(P)),
                                         egopose::from_unreal_rotation(ToQuat(Q)), Hand == EControllerHand::Left);
}
}  // namespace

UEgoPoseComponent::UEgoPoseComponent() { PrimaryComponentTick.bCanEverTick = true; }

void UEgoPoseComponent::BeginPlay() {
    Super::BeginPlay();
    FModuleManager::LoadModuleChecked<FWebSocketsModule>("WebSockets");
    Connect();
}

void UEgoPoseComponent::EndPlay(const EEndPlayReason::Type Reason) {
    if (Socket) Socket->Close();
    Super::EndPlay(Reason);
}

void UEgoPoseComponent::Connect() {
    bWelcomed = false;
    Socket = FWebSocketsModule::Get().CreateWebSocket(Url + TEXT("?session=") + Session, TEXT(""));
    Socket->OnConnected().AddLambda([this]() {
        egopose::Hello Hello{"input", TCHAR_TO_UTF8(*Session)};
        if (!Model.IsEmpty()) Hello.model = std::string(TCHAR_TO_UTF8(*Model));
        Hello.client = std::string("unreal/5");
        Send(egopose::encode(Hello));
    });
    Socket->OnRawMessage().AddUObject(this, &UEgoPoseComponent::OnRawMessage);
    auto Retry = [this]() {  // reconnect with a doubling backoff; the session (and its model) resumes
        bWelcomed = false;
        ReconnectAt = FPlatformTime::Seconds() + Backoff;
        Backoff = FMath::Min(Backoff * 2, 5.0);
    };
    Socket->OnConnectionError().AddLambda([Retry](const FString&) { Retry(); });
    Socket->OnClosed().AddLambda([Retry](int32, const FString&, bool) { Retry(); });
    Socket->Connect();
}

void UEgoPoseComponent::OnRawMessage(const void* Data, SIZE_T Size, SIZE_T BytesRemaining) {
    Partial.Append(static_cast<const uint8*>(Data), Size);
    if (BytesRemaining > 0) return;
    TArray<uint8> Bytes = MoveTemp(Partial);
    try {
        auto Handle = egopose::unpack(reinterpret_cast<const char*>(Bytes.GetData()), Bytes.Num());
        const std::string Type = egopose::message_type(Handle);
        if (Type == "welcome") {
            bWelcomed = true;
            Backoff = 0.25;
            if (KeptBoneLengths.Num() == egopose::kBoneCount) {  // before any hmd: every sample is served with it
                egopose::BoneLengths Lengths;
                for (int32 B = 0; B < KeptBoneLengths.Num(); ++B) Lengths[B] = KeptBoneLengths[B];
                Send(egopose::encode(egopose::SetBody{Lengths, false}));
            }
        } else if (Type == "models") {
            const egopose::Models Models = egopose::read_models(Handle);
            ActiveModel = UTF8_TO_TCHAR(Models.active.c_str());
            ModelNames.Reset();
            for (const egopose::ModelInfo& Info : Models.models) {
                ModelNames.Add(UTF8_TO_TCHAR(Info.name.c_str()));
                if (Info.name != Models.active) continue;
                const FString Sha256 = UTF8_TO_TCHAR(Info.sha256.value_or("").c_str());
                const FString EncoderSha256 = UTF8_TO_TCHAR(Info.encoder_sha256.value_or("").c_str());
                if (Sha256 != ActiveModelSha256 || EncoderSha256 != ActiveEncoderSha256)
                    UE_LOG(LogTemp, Log, TEXT("EgoPose: serving %s (sha256 %s, encoder %s)"), *ActiveModel,
                           Sha256.IsEmpty() ? TEXT("none: code") : *Sha256,
                           EncoderSha256.IsEmpty() ? TEXT("none") : *EncoderSha256);
                ActiveModelSha256 = Sha256;
                ActiveEncoderSha256 = EncoderSha256;
            }
        } else if (Type == "body") {
            const egopose::Body Body = egopose::read_body(Handle);
            if (Body.measured && !Body.given) MeasuredBoneLengths = TArray<float>(Body.bone_lengths_m.data(), egopose::kBoneCount);
        } else if (Type == "pose") {
            const egopose::Pose Pose = egopose::read_pose(Handle);
            const FTransform TrackingToWorld = UHeadMountedDisplayFunctionLibrary::GetTrackingToWorldTransform(this);
            Joints.SetNum(22);
            for (int32 J = 0; J < 22; ++J) {
                const egopose::Vec3 P = egopose::to_unreal_position(Pose.joints[3 * J], Pose.joints[3 * J + 1],
                                                                    Pose.joints[3 * J + 2]);
                Joints[J] = TrackingToWorld.TransformPosition(FVector(P.x, P.y, P.z));
            }
            const std::array<bool, 2> Planted = Pose.planted.value_or(std::array<bool, 2>{false, false});
            bLeftFootPlanted = Planted[0];
            bRightFootPlanted = Planted[1];
        } else if (Type == "error") {
            const egopose::Error Error = egopose::read_error(Handle);
            UE_LOG(LogTemp, Warning, TEXT("EgoPose: %hs: %hs"), Error.code.c_str(), Error.message.c_str());
            if (Error.ref_type == std::optional<std::string>("set_body")) KeptBoneLengths.Reset();  // refused: not again
        }  // other types (session, calibration, pong, later ones) are ignored here (PROTOCOL.md §8); the core reads them
    } catch (const std::exception& Exc) {
        UE_LOG(LogTemp, Warning, TEXT("EgoPose: unreadable server message: %hs"), Exc.what());
    }
}

void UEgoPoseComponent::TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTick) {
    Super::TickComponent(DeltaTime, TickType, ThisTick);
    if (!Socket->IsConnected() && ReconnectAt > 0 && FPlatformTime::Seconds() >= ReconnectAt) {
        ReconnectAt = 0;
        Connect();
    }
    if (bWelcomed) SendHmd();
    if (bDrawSkeleton && Joints.Num() == 22) {
        for (int32 J = 1; J < 22; ++J)
            DrawDebugLine(GetWorld(), Joints[kParents[J]], Joints[J], FColor::Cyan, false, -1, 0, 1.5f);
        // the foot joints (10 left, 11 right) the server holds planted
        if (bLeftFootPlanted) DrawDebugPoint(GetWorld(), Joints[10], 12.f, FColor::Orange, false, -1);
        if (bRightFootPlanted) DrawDebugPoint(GetWorld(), Joints[11], 12.f, FColor::Orange, false, -1);
    }
}

void UEgoPoseComponent::SendHmd() {
    egopose::Hmd Hmd;
    Hmd.seq = Seq++;
    Hmd.t_us = static_cast<int64_t>(FPlatformTime::Seconds() * 1e6);  // monotonic; only differences matter
    FRotator HeadRotation;
    FVector HeadPosition;  // tracking space, cm
    UHeadMountedDisplayFunctionLibrary::GetOrientationAndPosition(HeadRotation, HeadPosition);
    Hmd.head = egopose::pose_from_unreal(ToVec(HeadPosition), ToQuat(HeadRotation.Quaternion()));
    Hmd.valid[0] = UHeadMountedDisplayFunctionLibrary::IsHeadMountedDisplayConnected();
    bool bLeft = false, bRight = false;
    Hmd.left = Controller(this, EControllerHand::Left, bLeft);
    Hmd.right = Controller(this, EControllerHand::Right, bRight);
    Hmd.valid[1] = bLeft;
    Hmd.valid[2] = bRight;
    Send(egopose::encode(Hmd));
}

void UEgoPoseComponent::SelectModel(const FString& Name) {
    Send(egopose::encode(egopose::SelectModel{TCHAR_TO_UTF8(*Name)}));
}

void UEgoPoseComponent::RequestBody() { Send(egopose::encode(egopose::GetBody{})); }

void UEgoPoseComponent::Send(const msgpack::sbuffer& Buffer) {
    if (Socket && Socket->IsConnected()) Socket->Send(Buffer.data(), Buffer.size(), /*bIsBinary=*/true);
}
